// Console harness for the C# client (no Unity needed), driven by tests/test_unity_client.py:
//   Harness.exe parse FILE                      one output line per message line of FILE
//   Harness.exe subscribe URL SESSION TOKEN SECONDS   receive for SECONDS, one line per message
//   Harness.exe queue FILE                      FILE's messages through a 5-message client queue
// Each output line is JSON: what the C# client read, in Unity's frame where it converts.
using System;
using System.IO;
using System.Threading;
using Fingertrack;
using Newtonsoft.Json.Linq;

static class Harness
{
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
            foreach (var kv in f.Fingers)
                angles[kv.Key] = new JObject { { "mcp", kv.Value.Mcp }, { "second", kv.Key == "thumb" ? kv.Value.Ip : kv.Value.Pip }, { "mode", kv.Value.Mode } };
            o["fingers"] = angles;
            var unity = new JObject();
            foreach (var kv in f.Joints)
                unity[kv.Key] = new JObject { { "position", A(kv.Value.Position.ToUnity()) }, { "orientation", A(kv.Value.Orientation.ToUnity()) } };
            o["unity_joints"] = unity;
            if (f.PointingRay != null) o["unity_ray_direction"] = A(f.PointingRay.Direction.ToUnity());
            return o;
        }
        var g = m as GestureEvent;
        if (g != null) return new JObject { { "type", "gesture" }, { "t", g.T }, { "gesture", g.Gesture }, { "event", g.Event } };
        var e = m as ErrorMessage;
        if (e != null) return new JObject { { "type", "error" }, { "code", e.Code } };
        var h = (ServerHello)m;
        return new JObject { { "type", "hello" }, { "protocol", h.Protocol }, { "session", h.Session } };
    }

    static int Main(string[] args)
    {
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
        if (args.Length == 5 && args[0] == "subscribe")
        {
            var client = new FingertrackClient(args[1], args[2], args[3]);
            client.MaxQueued = int.MaxValue;      // the harness keeps every message (its first output waits for the JIT)
            client.OnProblem += text => Console.Error.WriteLine("problem: " + text);
            client.Start();
            var until = DateTime.UtcNow.AddSeconds(double.Parse(args[4], System.Globalization.CultureInfo.InvariantCulture));
            // "ready" once subscribed (the service's hello arrived), or given up waiting (refused, timeout)
            var wait = DateTime.UtcNow.AddSeconds(10);
            while (client.Hello == null && client.Refused == null && DateTime.UtcNow < wait) Thread.Sleep(5);
            Console.WriteLine(new JObject { { "type", "ready" }, { "subscribed", client.Hello != null } }.ToString(Newtonsoft.Json.Formatting.None));
            while (DateTime.UtcNow < until && client.Refused == null)
            {
                ServiceMessage m;
                while (client.TryDequeue(out m)) Console.WriteLine(Describe(m).ToString(Newtonsoft.Json.Formatting.None));
                Thread.Sleep(5);
            }
            var summary = new JObject { { "type", "summary" }, { "reconnects", client.Reconnects },
                                        { "bad_messages", client.BadMessages }, { "refused", client.Refused },
                                        { "hello_session", client.Hello != null ? client.Hello.Session : null } };
            client.Dispose();
            Console.WriteLine(summary.ToString(Newtonsoft.Json.Formatting.None));
            return 0;
        }
        Console.Error.WriteLine("usage: Harness.exe parse FILE | subscribe URL SESSION TOKEN SECONDS");
        return 2;
    }
}
