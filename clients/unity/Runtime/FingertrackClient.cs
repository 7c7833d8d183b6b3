// A subscriber to one hand's stream: WS /v1/stream/{session}?token=... (role "viewer").
// Receives on a background task, queues parsed messages for the caller's thread (Unity's main
// thread drains them in Update), and reconnects with exponential back-off after a lost
// connection, resubscribing to the same session (the state a VR client must not lose).
// A refusal (bad token, wrong role, unsupported protocol: close code 1008) is not retried.
// MessagePack (subprotocol "fingertrack.msgpack") by default: read straight from the received bytes
// with little allocation (FingertrackMsgPack.cs); JSON text when UseMessagePack is false.
// Dispose never blocks: it cancels, aborts the socket and returns; the loop ends on its own
// (State becomes Stopped).
using System;
using System.Collections.Concurrent;
using System.Diagnostics;
using System.IO;
using System.Net;
using System.Net.WebSockets;
using System.Text;
using System.Threading;
using System.Threading.Tasks;

namespace Fingertrack
{
    /// <summary>Where a client is: Connecting (first attempt), Connected (subscribed), Waiting (lost
    /// the connection, reconnecting after a back-off), Refused (the service said no: see Refused; not
    /// retried) or Stopped (disposed).</summary>
    public enum ConnectionState { Idle, Connecting, Connected, Waiting, Refused, Stopped }

    public sealed class FingertrackClient : IDisposable
    {
        public const string MsgPackSubprotocol = "fingertrack.msgpack";
        static readonly Stopwatch clock = Stopwatch.StartNew();

        /// <summary>The client's monotonic clock, s (what Frame.ReceivedAtS is measured on).</summary>
        public static double Now { get { return clock.Elapsed.TotalSeconds; } }

        /// <summary>Ask for MessagePack (allocation-light); set before Start.</summary>
        public bool UseMessagePack = true;

        /// <summary>The connection state (header comment). Changes are also reported by StateChanged,
        /// called on the receive task: a Unity component forwards them to the main thread.</summary>
        public ConnectionState State { get { return (ConnectionState)state; } }
        public event Action<ConnectionState> StateChanged;
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
        volatile ClientWebSocket socket;
        int reconnects, badMessages, state;

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

        /// <summary>The receive loop (completes after Dispose, a refusal or a fatal error).</summary>
        public Task Completion { get { return loop ?? Task.FromResult(0); } }

        void SetState(ConnectionState s)
        {
            if (Interlocked.Exchange(ref state, (int)s) == (int)s) return;
            var h = StateChanged;
            if (h != null) h(s);
        }

        /// <summary>Takes the next message, if any (non-blocking).</summary>
        public bool TryDequeue(out ServiceMessage message) { return Messages.TryDequeue(out message); }

        async Task Run(CancellationToken ct)
        {
            try { await Loop(ct).ConfigureAwait(false); }
            finally { SetState(Refused != null ? ConnectionState.Refused : ConnectionState.Stopped); }
        }

        async Task Loop(CancellationToken ct)
        {
            var delay = BackoffInitialS;
            var first = true;
            SetState(ConnectionState.Connecting);
            while (!ct.IsCancellationRequested && Refused == null)
            {
                using (var ws = new ClientWebSocket())
                {
                    socket = ws;
                    try
                    {
                        if (UseMessagePack) ws.Options.AddSubProtocol(MsgPackSubprotocol);
                        await ws.ConnectAsync(uri, ct).ConfigureAwait(false);
                        if (!first) Interlocked.Increment(ref reconnects);
                        first = false;
                        delay = BackoffInitialS;
                        SetState(ConnectionState.Connected);
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
                        if (ct.IsCancellationRequested) return;
                        var reason = await RefusalReason(ct).ConfigureAwait(false);
                        if (ct.IsCancellationRequested) return;
                        if (reason != null)
                        {
                            Refused = reason;
                            Problem("refused by the service: " + Refused);
                            return;
                        }
                        Problem("connection: " + e.Message);
                    }
                    finally { socket = null; }
                }
                if (ct.IsCancellationRequested) return;
                SetState(ConnectionState.Waiting);
                try { await Task.Delay(TimeSpan.FromSeconds(delay), ct).ConfigureAwait(false); }
                catch (OperationCanceledException) { return; }
                delay = Math.Min(delay * 2.0, BackoffMaxS);
            }
        }

        /// <summary>After a failed handshake: asks the service whether the token may read this
        /// session's data (GET /v1/sessions, the same roles as the stream). The service refuses a bad
        /// token or role before upgrading, and not every WebSocket implementation reports the HTTP
        /// status (Mono's does not). Returns the service's reason for a 401/403, else null (a network
        /// problem or a service still starting: retry). It waits for the answer (a service that has
        /// just answered the handshake answers this too, however busy it is; a time limit would take a
        /// slow refusal for a network problem and retry it), until the connection fails or Stop.</summary>
        async Task<string> RefusalReason(CancellationToken ct)
        {
            try
            {
                var req = (HttpWebRequest)WebRequest.Create(restBase + "/v1/sessions");
                req.Timeout = System.Threading.Timeout.Infinite;
                if (!string.IsNullOrEmpty(token)) req.Headers["Authorization"] = "Bearer " + token;
                using (ct.Register(req.Abort))
                using (await req.GetResponseAsync().ConfigureAwait(false)) { return null; }
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

        /// <summary>Largest message accepted, bytes (the service's own limit is 1 MiB).</summary>
        public int MaxMessageBytes = 1 << 20;

        async Task Receive(ClientWebSocket ws, CancellationToken ct)
        {
            // one growing buffer per connection: a message is read into it whole, then parsed in place
            var data = new byte[64 * 1024];
            var used = 0;
            while (ws.State == WebSocketState.Open)
            {
                if (used == data.Length)
                {
                    if (data.Length >= MaxMessageBytes) throw new ProtocolException("a message exceeds " + MaxMessageBytes + " bytes");
                    Array.Resize(ref data, Math.Min(2 * data.Length, MaxMessageBytes));
                }
                var r = await ws.ReceiveAsync(new ArraySegment<byte>(data, used, data.Length - used), ct).ConfigureAwait(false);
                if (r.MessageType == WebSocketMessageType.Close)
                {
                    try { await ws.CloseOutputAsync(WebSocketCloseStatus.NormalClosure, "", CancellationToken.None).ConfigureAwait(false); }
                    catch (Exception) { }
                    return;
                }
                used += r.Count;
                if (!r.EndOfMessage) continue;
                if (r.MessageType == WebSocketMessageType.Binary) HandleBinary(data, 0, used, Now);
                else Handle(Encoding.UTF8.GetString(data, 0, used));
                used = 0;
            }
        }

        /// <summary>One received MessagePack message (internal: the test harness feeds it).</summary>
        internal void HandleBinary(byte[] data, int offset, int count, double arrivalS)
        {
            ServiceMessage m;
            try { m = MsgPackProtocol.Parse(data, offset, count); }
            catch (ProtocolException e)
            {
                Interlocked.Increment(ref badMessages);
                Problem("unreadable message: " + e.Message);
                return;
            }
            Accept(m, arrivalS);
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
            Accept(m, Now);
        }

        void Accept(ServiceMessage m, double arrivalS)
        {
            var frame = m as Frame;
            if (frame != null) frame.ReceivedAtS = arrivalS;
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

        /// <summary>Stops receiving and drops the connection without waiting (safe on Unity's main
        /// thread); the receive loop then ends by itself (Completion, State Stopped).</summary>
        public void Dispose()
        {
            if (stop.IsCancellationRequested) return;
            stop.Cancel();
            var ws = socket;
            if (ws != null)
            {
                try { ws.Abort(); }
                catch (Exception) { }
            }
            if (loop == null) SetState(ConnectionState.Stopped);
        }
    }
}
