"""fingertrack service: hand model, simulator, estimators, pipeline and API."""
import os
import sys
import tempfile
from pathlib import Path


def _writable_dir(path: Path) -> bool:
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / f".probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
        return True
    except OSError:
        return False


def numba_cache_dir(environ=os.environ) -> str | None:
    """Where compiled numba kernels are cached: the first writable of ``NUMBA_CACHE_DIR`` (when set),
    the per-user cache (``$XDG_CACHE_HOME`` or ``~/.cache``, then ``fingertrack/numba``) and a
    per-user folder in the temporary directory; ``None`` if none is writable (e.g. a read-only root
    file system without a writable /tmp), in which case kernels are compiled without a cache. numba
    itself needs a writable cache folder: given an unwritable one it caches beside the package's
    source instead, and fails at import where that is read-only too."""
    candidates = []
    if environ.get("NUMBA_CACHE_DIR"):
        candidates.append(Path(environ["NUMBA_CACHE_DIR"]))
    base = environ.get("XDG_CACHE_HOME")
    if not base:
        try:
            base = str(Path.home() / ".cache")
        except RuntimeError:                # no home directory known
            base = None
    if base:
        candidates.append(Path(base) / "fingertrack" / "numba")
    uid = os.getuid() if hasattr(os, "getuid") else "user"
    candidates.append(Path(tempfile.gettempdir()) / f"fingertrack-numba-{uid}")
    return next((str(c) for c in candidates if _writable_dir(c)), None)


# numba reads its cache location when it is first imported, so this runs before any kernel module
_cache = numba_cache_dir()
if _cache is not None:
    os.environ["NUMBA_CACHE_DIR"] = _cache
else:
    os.environ.pop("NUMBA_CACHE_DIR", None)
if "numba" in sys.modules:          # imported before this package: it read the environment already
    sys.modules["numba"].core.config.reload_config()
JIT_CACHE = _cache is not None
"""Whether numba kernels may use ``cache=True`` (a writable cache folder exists)."""

KERNEL_FASTMATH = False
"""The numba kernels' fast-math licence: none, strict IEEE arithmetic (no fused multiply-add either).
numba links a copy of every kernel a kernel calls into the caller's code and optimises it again there;
a process that compiled the callee runs the callee's own code, one that loaded the caller from the
on-disk cache runs the caller's copy. With ``{"contract"}`` the two copies fused multiply-adds in
different places, so a replay's last bits depended on whether the cache was warm. Without fast-math
every copy computes the same IEEE results (``tests/test_determinism.py``)."""
