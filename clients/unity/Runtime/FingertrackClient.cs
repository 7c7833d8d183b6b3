// A subscriber to one hand's stream: WS /v1/stream/{session}?token=... (role "viewer").
// Receives on a background task, queues parsed messages for the caller's thread (Unity's main
// thread drains them in Update), and reconnects with exponential back-off after a lost
// connection, resubscribing to the same session (the state a VR client must not lose).
// A refusal (bad token, wrong role, unsupported protocol: close code 1008) is not retried.
using System;
using System.Collections.Concurrent;
using System.IO;
using System.Net;
using System.Net.WebSockets;
using System.Text;
using System.Threading;
using System.Threading.Tasks;

namespace Fingertrack
{
    public sealed class FingertrackClient : IDisposable
    {
        /// <summary>Parsed frames and gesture events (and error messages), in arrival order.</summary>
        public readonly ConcurrentQueue<ServiceMessage> Messages = new ConcurrentQueue<ServiceMessage>();
        /// <summary>The service's hello of the current connection (protocol version, session).</summary>
        public volatile ServerHello Hello;
        /// <summary>Connections made after the first (reconnects).</summary>
        public int Reconnects { get { return reconnects; } }
        /// <summary>Messages that could not be parsed (each also reported through OnProblem).</summary>
        public int BadMessages { get { return badMessages; } }
        /// <summary>Why the service refused the connection (then the client stops), or null.</summary>
        public volatile string Refused;
        /// <summary>Connection problems and unreadable messages, as text (called on the receive task).</summary>
        public event Action<string> OnProblem;
        /// <summary>Maximum messages kept unread; the oldest frames are dropped beyond it (a stalled
        /// main thread must not grow memory without bound), events never are.</summary>
        public int MaxQueued = 256;

        public double BackoffInitialS = 0.2, BackoffMaxS = 5.0;

        readonly Uri uri;
        readonly string restBase, token;
        readonly CancellationTokenSource stop = new CancellationTokenSource();
        Task loop;
        int reconnects, badMessages;

        /// <param name="baseUrl">the service, e.g. "http://127.0.0.1:8765" (ws:// and wss:// work too)</param>
        public FingertrackClient(string baseUrl, string session, string token)
        {
            if (string.IsNullOrEmpty(session)) throw new ArgumentException("session must be a non-empty name");
            restBase = baseUrl.TrimEnd('/').Replace("ws://", "http://").Replace("wss://", "https://");
            this.token = token;
            var b = restBase.Replace("http://", "ws://").Replace("https://", "wss://");
            var q = string.IsNullOrEmpty(token) ? "" : "?token=" + Uri.EscapeDataString(token);
            uri = new Uri(b + "/v1/stream/" + Uri.EscapeDataString(session) + q);
        }

        public void Start()
        {
            if (loop == null) loop = Task.Run(() => Run(stop.Token));
        }

        /// <summary>Takes the next message, if any (non-blocking).</summary>
        public bool TryDequeue(out ServiceMessage message) { return Messages.TryDequeue(out message); }

        async Task Run(CancellationToken ct)
        {
            var delay = BackoffInitialS;
            var first = true;
            while (!ct.IsCancellationRequested && Refused == null)
            {
                using (var ws = new ClientWebSocket())
                {
                    try
                    {
                        await ws.ConnectAsync(uri, ct).ConfigureAwait(false);
                        if (!first) Interlocked.Increment(ref reconnects);
                        first = false;
                        delay = BackoffInitialS;
                        await Receive(ws, ct).ConfigureAwait(false);
                        if (ws.CloseStatus == WebSocketCloseStatus.PolicyViolation)
                        {
                            Refused = ws.CloseStatusDescription ?? "refused";
                            Problem("refused by the service: " + Refused);
                            return;
                        }
                    }
                    catch (OperationCanceledException) { return; }
                    catch (Exception e)
                    {
                        var reason = RefusalReason();
                        if (reason != null)
                        {
                            Refused = reason;
                            Problem("refused by the service: " + Refused);
                            return;
                        }
                        Problem("connection: " + e.Message);
                    }
                }
                if (ct.IsCancellationRequested) return;
                try { await Task.Delay(TimeSpan.FromSeconds(delay), ct).ConfigureAwait(false); }
                catch (OperationCanceledException) { return; }
                delay = Math.Min(delay * 2.0, BackoffMaxS);
            }
        }

        /// <summary>After a failed handshake: asks the service whether the token may read this
        /// session's data (GET /v1/sessions, the same roles as the stream). The service refuses a bad
        /// token or role before upgrading, and not every WebSocket implementation reports the HTTP
        /// status (Mono's does not). Returns the service's reason for a 401/403, else null (a network
        /// problem or a service still starting: retry).</summary>
        string RefusalReason()
        {
            try
            {
                var req = (HttpWebRequest)WebRequest.Create(restBase + "/v1/sessions");
                req.Timeout = 2000;
                if (!string.IsNullOrEmpty(token)) req.Headers["Authorization"] = "Bearer " + token;
                using (req.GetResponse()) { return null; }
            }
            catch (WebException e)
            {
                var http = e.Response as HttpWebResponse;
                if (http == null) return null;
                using (http)
                {
                    var code = (int)http.StatusCode;
                    if (code != 401 && code != 403) return null;
                    string body;
                    using (var reader = new StreamReader(http.GetResponseStream())) body = reader.ReadToEnd();
                    string detail = null;
                    try { detail = (string)Newtonsoft.Json.Linq.JObject.Parse(body)["detail"]; }
                    catch (Exception) { }
                    return "HTTP " + code + ": " + (detail ?? body);
                }
            }
            catch (Exception) { return null; }
        }

        async Task Receive(ClientWebSocket ws, CancellationToken ct)
        {
            var buffer = new ArraySegment<byte>(new byte[64 * 1024]);
            var text = new MemoryStream();
            while (ws.State == WebSocketState.Open)
            {
                var r = await ws.ReceiveAsync(buffer, ct).ConfigureAwait(false);
                if (r.MessageType == WebSocketMessageType.Close)
                {
                    try { await ws.CloseOutputAsync(WebSocketCloseStatus.NormalClosure, "", CancellationToken.None).ConfigureAwait(false); }
                    catch (Exception) { }
                    return;
                }
                text.Write(buffer.Array, buffer.Offset, r.Count);
                if (!r.EndOfMessage) continue;
                var json = Encoding.UTF8.GetString(text.GetBuffer(), 0, (int)text.Length);
                text.SetLength(0);
                Handle(json);
            }
        }

        /// <summary>One received text message: parsed and queued (internal: the test harness feeds it).</summary>
        internal void Handle(string json)
        {
            ServiceMessage m;
            try { m = Protocol.Parse(json); }
            catch (ProtocolException e)
            {
                Interlocked.Increment(ref badMessages);
                Problem("unreadable message: " + e.Message);
                return;
            }
            var hello = m as ServerHello;
            if (hello != null) { Hello = hello; return; }
            Messages.Enqueue(m);
            if (Messages.Count > MaxQueued) DropOldestFrame();
        }

        void DropOldestFrame()
        {
            // frames are superseded by newer ones; events and errors are kept in order
            var keep = new ConcurrentQueue<ServiceMessage>();
            ServiceMessage m;
            var dropped = false;
            while (Messages.TryDequeue(out m))
            {
                if (!dropped && m is Frame) { dropped = true; continue; }
                keep.Enqueue(m);
            }
            while (keep.TryDequeue(out m)) Messages.Enqueue(m);
        }

        void Problem(string text)
        {
            var h = OnProblem;
            if (h != null) h(text);
        }

        /// <summary>Stops receiving and closes the connection.</summary>
        public void Dispose()
        {
            stop.Cancel();
            try { if (loop != null) loop.Wait(2000); }
            catch (AggregateException) { }
            stop.Dispose();
        }
    }
}
