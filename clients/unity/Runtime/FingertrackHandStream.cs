// One hand's stream for a scene: a FingertrackClient whose messages are drained on the main thread
// (Poll), frames kept for interpolation to the render time, gesture events, errors and connection
// state changes raised as C# events on the main thread. No UnityEngine dependency: FingertrackHand,
// the XR Hands provider and the console harness share it.
using System;

namespace Fingertrack
{
    public sealed class HandStream : IHandSource, IDisposable
    {
        public readonly FingertrackClient Client;
        public readonly FrameInterpolator Interpolator;

        /// <summary>Raised by Poll, on the caller's (main) thread.</summary>
        public event Action<GestureEvent> Gesture;
        public event Action<ErrorMessage> Error;
        public event Action<ConnectionState> StateChanged;

        ConnectionState reported = ConnectionState.Idle;

        public HandStream(string baseUrl, string session, string token, FrameInterpolator interpolator = null)
            : this(new FingertrackClient(baseUrl, session, token), interpolator) { }

        public HandStream(FingertrackClient client, FrameInterpolator interpolator = null)
        {
            Client = client;
            Interpolator = interpolator ?? new FrameInterpolator();
        }

        public ConnectionState State { get { return Client.State; } }
        /// <summary>The service's reason for refusing (token, role, protocol), or null.</summary>
        public string Refused { get { return Client.Refused; } }
        public Frame Newest { get { return Interpolator.Newest; } }

        public void Start() { Client.Start(); }

        /// <summary>Drains the received messages: frames to the interpolator, events raised in order.</summary>
        public void Poll()
        {
            ServiceMessage m;
            while (Client.TryDequeue(out m))
            {
                var f = m as Frame;
                if (f != null) { Interpolator.Add(f); continue; }
                var g = m as GestureEvent;
                if (g != null) { var h = Gesture; if (h != null) h(g); continue; }
                var e = m as ErrorMessage;
                if (e != null) { var h = Error; if (h != null) h(e); }
            }
            var now = Client.State;
            if (now != reported)
            {
                reported = now;
                var h = StateChanged;
                if (h != null) h(now);
            }
        }

        /// <summary>Polls, then samples the hand at the client's time localS (interpolated).</summary>
        public bool Sample(double localS, HandSample into)
        {
            Poll();
            return Interpolator.Sample(localS, into);
        }

        /// <summary>Non-blocking (FingertrackClient.Dispose).</summary>
        public void Dispose() { Client.Dispose(); }
    }
}
