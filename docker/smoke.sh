#!/usr/bin/env bash
# Smoke test of the service image: build it with docker or podman, start it, and check /health, that
# the startup lines reach the container log, a glove stream seen by a subscriber, and a recording
# that 'fingertrack replay' reads. Exit 0: all passed; 1: a check failed; 3: nothing could be tested
# here (no container engine, the base image neither stored nor reachable, or an engine that builds but
# cannot start containers).
#   docker/smoke.sh                 (ENGINE=docker or ENGINE=podman to choose; PORT=18765 by default)
set -euo pipefail
cd "$(dirname "$0")/.."

engine_works() { command -v "$1" >/dev/null 2>&1 && "$1" info >/dev/null 2>&1; }
ENGINE="${ENGINE:-}"
if [ -z "$ENGINE" ]; then
    for candidate in docker podman; do
        if engine_works "$candidate"; then ENGINE="$candidate"; break; fi
    done
fi
if [ -z "$ENGINE" ]; then
    for candidate in docker podman; do
        if command -v "$candidate" >/dev/null 2>&1; then
            echo "smoke: '$candidate' is installed but cannot reach a container engine ('$candidate info' failed)" >&2
        fi
    done
    echo "smoke: neither docker nor podman can run containers here; nothing was built or tested" >&2
    exit 3
fi

PORT="${PORT:-18765}"
IMAGE="fingertrack:smoke"
NAME="fingertrack-smoke-$$"
SOURCE="smoke-source-$RANDOM$RANDOM"
VIEWER="smoke-viewer-$RANDOM$RANDOM"
ADMIN="smoke-admin-$RANDOM$RANDOM$RANDOM"
FORMAT=()
[ "$ENGINE" = podman ] && FORMAT=(--format docker)    # OCI format would drop the HEALTHCHECK

fail() { echo "smoke: FAILED: $*" >&2; "$ENGINE" logs "$NAME" >&2 || true; exit 1; }
cleanup() { "$ENGINE" rm -f "$NAME" >/dev/null 2>&1 || true; }
trap cleanup EXIT

BASE="python:3.11-slim"
if ! "$ENGINE" image inspect "$BASE" >/dev/null 2>&1 && ! "$ENGINE" pull "$BASE" >/dev/null 2>&1; then
    echo "smoke: $ENGINE works, but the base image $BASE is neither in its store nor reachable (offline?);" \
         "nothing was built or tested" >&2
    exit 3
fi

echo "smoke: building $IMAGE with $ENGINE"
start=$(date +%s)
# BUILD_OPTS: extra build options, e.g. --pull=never to use a python:3.11-slim already in the store
# shellcheck disable=SC2086
"$ENGINE" build "${FORMAT[@]}" ${BUILD_OPTS:-} -f docker/Dockerfile -t "$IMAGE" . \
    || { echo "smoke: FAILED: the image did not build (is the base image python:3.11-slim reachable?)" >&2; exit 1; }
size=$("$ENGINE" image inspect "$IMAGE" --format '{{.Size}}')
echo "smoke: built in $(( $(date +%s) - start )) s; image size $(( size / 1000000 )) MB"
if ! "$ENGINE" run --rm "$IMAGE" true; then
    echo "smoke: the image was built, but $ENGINE cannot start containers on this machine; nothing was run" >&2
    exit 3
fi
for lib in matplotlib tqdm; do
    if "$ENGINE" run --rm "$IMAGE" python -c "import $lib" >/dev/null 2>&1; then fail "$lib is in the runtime image"; fi
done
[ "$("$ENGINE" run --rm "$IMAGE" id -u)" != 0 ] || fail "the image runs as root"

"$ENGINE" run -d --name "$NAME" -p "127.0.0.1:$PORT:8765" \
    -e FINGERTRACK_ADMIN_TOKEN="$ADMIN" \
    -e FINGERTRACK_TOKENS="{\"$SOURCE\":\"source\",\"$VIEWER\":\"viewer\"}" \
    -e FINGERTRACK_RECORD_ALL=true "$IMAGE" >/dev/null
for _ in $(seq 120); do
    if curl -fsS "http://127.0.0.1:$PORT/health" >/dev/null 2>&1; then break; fi
    sleep 0.5
done
curl -fsS "http://127.0.0.1:$PORT/health" >/dev/null || fail "/health does not answer on port $PORT"
echo "smoke: /health ok"
logs=$("$ENGINE" logs "$NAME" 2>&1)
grep -q "listening on" <<<"$logs" || fail "the startup lines are not in the container log (buffered output?)"
grep -q "$ADMIN" <<<"$logs" && fail "the configured admin token is printed in the log"
echo "smoke: startup lines in the log, configured admin token not printed"

# a glove streams a gesture sequence while a subscriber watches (both inside the container)
"$ENGINE" exec "$NAME" sh -c "timeout 120 fingertrack watch --url http://127.0.0.1:8765 --token $VIEWER \
    --session smoke --count 20 --every 0.2 > /tmp/watch.txt 2>&1 &"
sleep 2
"$ENGINE" exec "$NAME" fingertrack glove --url http://127.0.0.1:8765 --token "$SOURCE" --session smoke \
    --motion sequence --noise white || fail "the glove could not stream"
frames=$("$ENGINE" exec "$NAME" python -c "
import json, urllib.request
req = urllib.request.Request('http://127.0.0.1:8765/v1/sessions', headers={'Authorization': 'Bearer $ADMIN'})
print(next(s['frames_out'] for s in json.load(urllib.request.urlopen(req)) if s['session'] == 'smoke'))")
[ "$frames" -gt 0 ] || fail "the session produced no frames"
"$ENGINE" exec "$NAME" sh -c "grep -q . /tmp/watch.txt" || fail "the subscriber printed nothing"
echo "smoke: stream ok ($frames frames)"

recording=$("$ENGINE" exec "$NAME" sh -c "ls /recordings/smoke-*.jsonl | head -1")
[ -n "$recording" ] || fail "no recording in /recordings"
"$ENGINE" stop "$NAME" >/dev/null                    # flushes and closes the recording
"$ENGINE" start "$NAME" >/dev/null
"$ENGINE" exec "$NAME" fingertrack replay "$recording" || fail "fingertrack replay cannot read $recording"
echo "smoke: recording $recording replays"
echo "smoke: all checks passed ($ENGINE)"
