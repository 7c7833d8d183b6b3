// Console harness for the C# client (no Unity needed), driven by tests/test_unity_client.py:
//   Harness.exe parse FILE                      one output line per message line of FILE (JSON)
//   Harness.exe parse-msgpack FILE              the same for FILE's MessagePack messages (each after a
//                                               4-byte big-endian length)
//   Harness.exe alloc FILE REPEATS              bytes allocated per frame parsed, MessagePack and JSON
//   Harness.exe alloc-client FILE WARMUP        bytes allocated per frame through the client's whole path
//   Harness.exe interp FILE                     frames with arrival times, then queries: interpolated poses
//   Harness.exe subscribe URL SESSION TOKEN SECONDS [json]   receive until stdin says "until SEQ" and
//                                               that frame arrived (at most SECONDS), one line per message
//   Harness.exe queue FILE                      FILE's messages through a 5-message client queue
//   Harness.exe dispose URL                     start, dispose at once, wait for the loop to end
// With FINGERTRACK_XR_HANDS (Harness.XRHands.cs): xrhands LEFT RIGHT, the XR Hands provider fed by
// two MessagePack frame files.
// Each output line is JSON: what the C# client read, in Unity's frame where it converts.
using System;
using System.Collections.Generic;
using System.Globalization;
using System.IO;
using System.Threading;
using Fingertrack;
using Newtonsoft.Json.Linq;

static partial class Harness
{
    static void Print(JObject o) { Console.WriteLine(o.ToString(Newtonsoft.Json.Formatting.None)); }

    /// <summary>MessagePack messages of a file, each after its 4-byte big-endian length.</summary>
    static List<ArraySegment<byte>> ReadFramed(string path)
    {
        var data = File.ReadAllBytes(path);
        var list = new List<ArraySegment<byte>>();
        for (var at = 0; at < data.Length;)
        {
            var n = (data[at] << 24) | (data[at + 1] << 16) | (data[at + 2] << 8) | data[at + 3];
            list.Add(new ArraySegment<byte>(data, at + 4, n));
            at += 4 + n;
        }
        return list;
    }

    static JArray Joint(JointPose j)
    {
        return new JArray(A(j.Position.ToUnity()), A(j.Orientation.ToUnity()),
                          double.IsNaN(j.Radius) ? null : (JToken)j.Radius, j.Tracked);
    }

    static JArray A(Vec3 v) { return new JArray(v.X, v.Y, v.Z); }
    static JArray A(Quat q) { return new JArray(q.X, q.Y, q.Z, q.W); }

    static JObject Describe(ServiceMessage m)
    {
        var f = m as Frame;
        if (f != null)
        {
            var o = new JObject { { "type", "frame" }, { "t", f.T }, { "seq", f.Seq }, { "hand", f.Hand },
                                  { "active", f.ActiveGesture }, { "grab", f.GrabStrength } };
            var angles = new JObject();
            for (var i = 0; i < Protocol.FingerCount; i++)
            {
                var a = f.Fingers[i];
                if (a == null) continue;
                var name = Protocol.FingerNames[i];
                angles[name] = new JObject { { "mcp", a.Mcp }, { "second", name == "thumb" ? a.Ip : a.Pip }, { "mode", a.Mode } };
            }
            o["fingers"] = angles;
            var unity = new JObject();
            for (var i = 0; i < Protocol.JointCount; i++)
            {
                if (!f.HasJoint(i)) continue;
                var j = f.Joints[i];
                unity[Protocol.JointNames[i]] = new JObject {
                    { "position", A(j.Position.ToUnity()) }, { "orientation", A(j.Orientation.ToUnity()) },
                    { "radius", double.IsNaN(j.Radius) ? null : (JToken)j.Radius }, { "tracked", j.Tracked } };
            }
            o["unity_joints"] = unity;
            o["optics"] = f.Optics;
            o["pinch"] = f.PinchStrength;
            if (f.PointingRay != null) o["unity_ray_direction"] = A(f.PointingRay.Direction.ToUnity());
            return o;
        }
        var g = m as GestureEvent;
        if (g != null)
        {
            var o = new JObject { { "type", "gesture" }, { "t", g.T }, { "gesture", g.Gesture }, { "event", g.Event }, { "confidence", g.Confidence } };
            if (g.Ray != null) o["unity_ray_direction"] = A(g.Ray.Direction.ToUnity());
            return o;
        }
        var e = m as ErrorMessage;
        if (e != null) return new JObject { { "type", "error" }, { "code", e.Code }, { "detail", e.Detail } };
        var h = (ServerHello)m;
        return new JObject { { "type", "hello" }, { "protocol", h.Protocol }, { "session", h.Session } };
    }

    static int Main(string[] args)
    {
        if (args.Length == 2 && args[0] == "parse-msgpack")
        {
            foreach (var m in ReadFramed(args[1]))
            {
                try { Print(Describe(MsgPackProtocol.Parse(m.Array, m.Offset, m.Count))); }
                catch (ProtocolException ex) { Print(new JObject { { "problem", ex.Message } }); }
            }
            return 0;
        }
        if (args.Length == 3 && args[0] == "alloc") return Alloc(ReadFramed(args[1]), int.Parse(args[2], CultureInfo.InvariantCulture));
        if (args.Length == 3 && args[0] == "alloc-client") return AllocClient(ReadFramed(args[1]), int.Parse(args[2], CultureInfo.InvariantCulture));
        if (args.Length == 2 && args[0] == "interp") return Interp(args[1]);
        if (args.Length == 2 && args[0] == "dispose") return DisposeAtOnce(args[1]);
        if (args.Length == 3 && args[0] == "xrhands") return XRHands(args[1], args[2]);
        if (args.Length == 2 && args[0] == "parse")
        {
            foreach (var line in File.ReadAllLines(args[1]))
            {
                try { Console.WriteLine(Describe(Protocol.Parse(line)).ToString(Newtonsoft.Json.Formatting.None)); }
                catch (ProtocolException ex) { Console.WriteLine(new JObject { { "problem", ex.Message } }.ToString(Newtonsoft.Json.Formatting.None)); }
            }
            return 0;
        }
        if (args.Length == 2 && args[0] == "queue")
        {
            // the bounded queue: messages of FILE fed as if received, with room for 5
            var client = new FingertrackClient("http://127.0.0.1:1", "queue", "");
            client.MaxQueued = 5;
            foreach (var line in File.ReadAllLines(args[1])) client.Handle(line);
            ServiceMessage m;
            while (client.TryDequeue(out m)) Console.WriteLine(Describe(m).ToString(Newtonsoft.Json.Formatting.None));
            return 0;
        }
        if ((args.Length == 5 || args.Length == 6) && args[0] == "subscribe")
        {
            var client = new FingertrackClient(args[1], args[2], args[3]);
            client.UseMessagePack = args.Length == 5;
            var states = new JArray();
            client.StateChanged += st => { lock (states) states.Add(st.ToString()); };
            client.MaxQueued = int.MaxValue;      // the harness keeps every message (its first output waits for the JIT)
            client.OnProblem += text => Console.Error.WriteLine("problem: " + text);
            client.Start();
            var deadline = DateTime.UtcNow.AddSeconds(double.Parse(args[4], CultureInfo.InvariantCulture));
            // "ready" once subscribed (the service's hello arrived), or given up waiting (refused, timeout)
            var wait = DateTime.UtcNow.AddSeconds(10);
            while (client.Hello == null && client.Refused == null && DateTime.UtcNow < wait) Thread.Sleep(5);
            Console.WriteLine(new JObject { { "type", "ready" }, { "subscribed", client.Hello != null } }.ToString(Newtonsoft.Json.Formatting.None));
            Console.Out.Flush();
            // stdin may say "until SEQ": stop once that frame has arrived (SECONDS only bounds a failure)
            long until = long.MaxValue, newest = -1;
            var reader = new Thread(() =>
            {
                string line;
                while ((line = Console.In.ReadLine()) != null)
                    if (line.StartsWith("until ")) Interlocked.Exchange(ref until, long.Parse(line.Substring(6), CultureInfo.InvariantCulture));
            }) { IsBackground = true };
            reader.Start();
            while (DateTime.UtcNow < deadline && client.Refused == null && newest < Interlocked.Read(ref until))
            {
                ServiceMessage m;
                while (client.TryDequeue(out m))
                {
                    var f = m as Frame;
                    if (f != null) newest = Math.Max(newest, f.Seq);
                    Console.WriteLine(Describe(m).ToString(Newtonsoft.Json.Formatting.None));
                }
                Thread.Sleep(5);
            }
            var summary = new JObject { { "type", "summary" }, { "reconnects", client.Reconnects },
                                        { "bad_messages", client.BadMessages }, { "refused", client.Refused },
                                        { "hello_session", client.Hello != null ? client.Hello.Session : null } };
            client.Dispose();
            client.Completion.Wait();
            lock (states) summary["states"] = new JArray(states);
            Console.WriteLine(summary.ToString(Newtonsoft.Json.Formatting.None));
            return 0;
        }
        Console.Error.WriteLine("usage: see the header of Harness.cs");
        return 2;
    }

    /// <summary>Bytes allocated on this thread per frame parsed: the frames parsed REPEATS times
    /// after a warm-up pass (JIT, static tables), MessagePack and then the same frames as JSON text
    /// (text decoded from UTF-8 as the client does).</summary>
    static int Alloc(List<ArraySegment<byte>> frames, int repeats)
    {
        var json = new List<byte[]>();
        foreach (var m in frames)
        {
            var f = (Frame)MsgPackProtocol.Parse(m.Array, m.Offset, m.Count);
            json.Add(System.Text.Encoding.UTF8.GetBytes(ToJson(f)));
        }
        foreach (var m in frames) MsgPackProtocol.Parse(m.Array, m.Offset, m.Count);
        var before = GC.GetAllocatedBytesForCurrentThread();
        for (var r = 0; r < repeats; r++)
            foreach (var m in frames) MsgPackProtocol.Parse(m.Array, m.Offset, m.Count);
        var msgpack = (double)(GC.GetAllocatedBytesForCurrentThread() - before) / (repeats * frames.Count);
        foreach (var b in json) Protocol.Parse(System.Text.Encoding.UTF8.GetString(b));
        before = GC.GetAllocatedBytesForCurrentThread();
        for (var r = 0; r < repeats; r++)
            foreach (var b in json) Protocol.Parse(System.Text.Encoding.UTF8.GetString(b));
        var text = (double)(GC.GetAllocatedBytesForCurrentThread() - before) / (repeats * frames.Count);
        long size = 0;
        foreach (var m in frames) size += m.Count;
        Print(new JObject { { "frames", frames.Count }, { "repeats", repeats }, { "msgpack_bytes_per_frame", msgpack },
                            { "json_bytes_per_frame", text }, { "msgpack_message_bytes", (double)size / frames.Count } });
        return 0;
    }

    /// <summary>Per frame, what a scene's hand costs from the received bytes on: the client reads the
    /// message and queues it (FingertrackClient.HandleBinary, as its receive loop does), the main
    /// thread drains the queue into the interpolator and samples the hand at a render time
    /// (HandStream.Sample, once per frame as at 90 Hz); all on this thread, so every allocation is
    /// counted. The received bytes land in the client's reused buffer. The first WARMUP frames (the
    /// JIT, the queue's first segment) are not counted.</summary>
    static int AllocClient(List<ArraySegment<byte>> frames, int warmup)
    {
        var client = new FingertrackClient("http://127.0.0.1:1", "alloc", "");
        var stream = new HandStream(client);
        var sample = new HandSample();
        long before = 0, interpolated = 0;
        var arrival = 0.0;
        for (var k = 0; k < frames.Count; k++)
        {
            if (k == warmup) before = GC.GetAllocatedBytesForCurrentThread();
            var m = frames[k];
            arrival += 1.0 / 90.0;
            client.HandleBinary(m.Array, m.Offset, m.Count, arrival);
            if (!stream.Sample(arrival, sample)) throw new InvalidOperationException("no hand sampled");
            if (!sample.Held && k >= warmup) interpolated++;
        }
        var perFrame = (double)(GC.GetAllocatedBytesForCurrentThread() - before) / (frames.Count - warmup);
        Print(new JObject { { "frames", frames.Count - warmup }, { "interpolated", interpolated },
                            { "client_bytes_per_frame", perFrame }, { "bad_messages", client.BadMessages },
                            { "newest_seq", stream.Newest.Seq } });
        return 0;
    }

    /// <summary>A frame back as protocol JSON (for the JSON side of Alloc).</summary>
    static string ToJson(Frame f)
    {
        var joints = new JObject();
        for (var i = 0; i < Protocol.JointCount; i++)
        {
            if (!f.HasJoint(i)) continue;
            var j = f.Joints[i];
            joints[Protocol.JointNames[i]] = new JObject { { "position", A(j.Position) }, { "orientation", A(j.Orientation) },
                                                           { "radius", j.Radius }, { "tracked", j.Tracked } };
        }
        var fingers = new JObject();
        for (var i = 0; i < Protocol.FingerCount; i++)
        {
            var a = f.Fingers[i];
            if (a == null) continue;
            var o = new JObject { { "mcp", a.Mcp }, { "mode", a.Mode } };
            if (!double.IsNaN(a.Pip)) o["pip"] = a.Pip;
            if (!double.IsNaN(a.Dip)) o["dip"] = a.Dip;
            if (!double.IsNaN(a.Ip)) o["ip"] = a.Ip;
            fingers[Protocol.FingerNames[i]] = o;
        }
        return new JObject { { "type", "frame" }, { "t", f.T }, { "seq", f.Seq }, { "hand", f.Hand }, { "fingers", fingers },
                             { "joints", joints }, { "status", new JObject { { "optics", f.Optics } } },
                             { "gesture", new JObject { { "active", f.ActiveGesture }, { "grab_strength", f.GrabStrength },
                                                        { "pinch_strength", f.PinchStrength } } } }.ToString(Newtonsoft.Json.Formatting.None);
    }

    /// <summary>FILE: JSON lines, frames with an extra "arrival" (client clock, s), then
    /// {"query": localS, "delay": s}: per query the estimated offset and the interpolated hand.</summary>
    static int Interp(string path)
    {
        var interp = new FrameInterpolator();
        var sample = new HandSample();
        foreach (var line in File.ReadAllLines(path))
        {
            if (string.IsNullOrWhiteSpace(line)) continue;
            var o = JObject.Parse(line);
            if (o["query"] != null)
            {
                interp.DelayS = (double)o["delay"];
                var ok = interp.Sample((double)o["query"], sample);
                var joints = new JObject();
                for (var i = 0; i < Protocol.JointCount; i++)
                    if ((sample.JointPresent & (1 << i)) != 0)
                        joints[Protocol.JointNames[i]] = new JObject { { "position", A(sample.Positions[i]) },
                            { "orientation", A(sample.Orientations[i]) }, { "tracked", sample.Tracked[i] },
                            { "radius", double.IsNaN(sample.Radii[i]) ? null : (JToken)sample.Radii[i] } };
                Print(new JObject { { "ok", ok }, { "offset", interp.Clock.OffsetS }, { "source_t", sample.SourceT },
                                    { "held", sample.Held }, { "joints", joints } });
                continue;
            }
            var f = (Frame)Protocol.Parse(line);
            f.ReceivedAtS = (double)o["arrival"];
            interp.Add(f);
        }
        return 0;
    }

    /// <summary>Starts a client, disposes it at once from this thread and reports what happened.</summary>
    static int DisposeAtOnce(string url)
    {
        var client = new FingertrackClient(url, "dispose", "");
        var states = new List<string>();
        var connecting = new ManualResetEventSlim();
        client.StateChanged += st => { lock (states) states.Add(st.ToString()); if (st == ConnectionState.Connecting) connecting.Set(); };
        client.Start();
        connecting.Wait();                     // the loop is inside its first connection attempt
        client.Dispose();
        var returned = !client.Completion.IsCompleted;   // informational: whether Dispose returned before the loop ended
        client.Completion.Wait();
        lock (states) Print(new JObject { { "states", new JArray(states) }, { "dispose_returned_first", returned },
                                          { "final", client.State.ToString() } });
        return 0;
    }
}
