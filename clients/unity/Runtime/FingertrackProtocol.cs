// fingertrack protocol v1, service -> VR client: typed messages parsed from the wire's JSON
// (see DESIGN.md "Wire protocol v1"). No UnityEngine dependency: the same code runs in Unity
// and in the console harness that the Python tests drive against a real service.
//
// Frames: the service's world frame is OpenXR stage space (right-handed, +Y up, metres);
// Unity's is left-handed (+Y up, +Z forward). ToUnity* mirror the Z axis: a position (x, y, z)
// becomes (x, y, -z) and a rotation [x, y, z, w] becomes [-x, -y, z, w], the conversion the
// Unity OpenXR plugin applies to OpenXR poses.
using System;
using System.Collections.Generic;
using Newtonsoft.Json.Linq;

namespace Fingertrack
{
    /// <summary>A 3-vector as sent on the wire (OpenXR stage space).</summary>
    public struct Vec3
    {
        public double X, Y, Z;
        public Vec3(double x, double y, double z) { X = x; Y = y; Z = z; }
        /// <summary>The same point or direction in Unity's left-handed frame (Z mirrored).</summary>
        public Vec3 ToUnity() { return new Vec3(X, Y, -Z); }
    }

    /// <summary>A unit quaternion [x, y, z, w] as sent on the wire.</summary>
    public struct Quat
    {
        public double X, Y, Z, W;
        public Quat(double x, double y, double z, double w) { X = x; Y = y; Z = z; W = w; }
        /// <summary>The same rotation in Unity's left-handed frame (Z mirrored).</summary>
        public Quat ToUnity() { return new Quat(-X, -Y, Z, W); }
    }

    /// <summary>One OpenXR joint: pose in the service's stage space, radius and whether it is
    /// measured now. Radius is NaN and Tracked true when the service does not send them (older
    /// services: the fields are optional in protocol v1).</summary>
    public struct JointPose
    {
        public Vec3 Position;
        public Quat Orientation;
        /// <summary>Joint centre to skin, metres (NaN: not sent).</summary>
        public double Radius;
        /// <summary>False while the pose is held or inferred (optics occluded, finger without a live sensor).</summary>
        public bool Tracked;
    }

    /// <summary>Joint angles of one finger, radians (flexion positive); the thumb has Mcp and Ip.</summary>
    public sealed class FingerAngles
    {
        public double Mcp, Pip, Dip, Ip;
        /// <summary>Estimator mode: "slow", "fast", "fused" or "none".</summary>
        public string Mode;
    }

    public abstract class ServiceMessage
    {
        public double T;
    }

    public sealed class Frame : ServiceMessage
    {
        public long Seq;
        public string Hand;
        /// <summary>Angles per finger in Protocol.FingerNames order (thumb, index, middle, ring, little); null where not sent.</summary>
        public readonly FingerAngles[] Fingers = new FingerAngles[Protocol.FingerCount];
        /// <summary>The 26 XR_EXT_hand_tracking joints in XrHandJointEXT order (Protocol.JointNames:
        /// palm, wrist, thumb_metacarpal, ..., little_tip); JointPresent says which were sent.</summary>
        public readonly JointPose[] Joints = new JointPose[Protocol.JointCount];
        /// <summary>Bit i set: Joints[i] was sent.</summary>
        public int JointPresent;
        /// <summary>The gesture layer's continuous values: active gesture (or null), grab and pinch strength.</summary>
        public string ActiveGesture;
        public double GrabStrength, PinchStrength;
        /// <summary>The pointing ray while pointing (null otherwise).</summary>
        public Ray PointingRay;
        /// <summary>status.optics: "tracking", "occluded" or "waiting" (null if not sent).</summary>
        public string Optics;
        /// <summary>The service's whole status object (JSON messages only; null for MessagePack,
        /// whose reader keeps only Optics to stay allocation-light).</summary>
        public JObject Status;
        /// <summary>When the client received it, seconds on the client's monotonic clock
        /// (FingertrackClient.Now); NaN if not received by a client.</summary>
        public double ReceivedAtS = double.NaN;

        public bool HasJoint(int index) { return (JointPresent & (1 << index)) != 0; }

        /// <summary>The joint of that OpenXR name ("index_tip", ...), if it was sent.</summary>
        public bool TryGetJoint(string name, out JointPose pose)
        {
            var i = Array.IndexOf(Protocol.JointNames, name);
            if (i < 0 || !HasJoint(i)) { pose = default(JointPose); return false; }
            pose = Joints[i];
            return true;
        }

        /// <summary>The angles of that finger ("thumb", "index", ...), or null.</summary>
        public FingerAngles Finger(string name)
        {
            var i = Array.IndexOf(Protocol.FingerNames, name);
            return i < 0 ? null : Fingers[i];
        }
    }

    public sealed class Ray
    {
        public Vec3 Origin, Direction;
    }

    public sealed class GestureEvent : ServiceMessage
    {
        /// <summary>"point", "grasp", "pinch" or "open".</summary>
        public string Gesture;
        /// <summary>"start" or "end".</summary>
        public string Event;
        public double Confidence;
        public Ray Ray;
    }

    public sealed class ErrorMessage : ServiceMessage
    {
        public string Code, Detail;
    }

    public sealed class ServerHello : ServiceMessage
    {
        public int Protocol;
        public string Server, Session;
    }

    /// <summary>The message could not be read as protocol v1; the text says what was wrong.</summary>
    public sealed class ProtocolException : Exception
    {
        public ProtocolException(string message) : base(message) { }
    }

    public static class Protocol
    {
        public const int Version = 1;
        public const int JointCount = 26, FingerCount = 5;

        /// <summary>OpenXR XR_EXT_hand_tracking joint names in XrHandJointEXT order.</summary>
        public static readonly string[] JointNames = {
            "palm", "wrist",
            "thumb_metacarpal", "thumb_proximal", "thumb_distal", "thumb_tip",
            "index_metacarpal", "index_proximal", "index_intermediate", "index_distal", "index_tip",
            "middle_metacarpal", "middle_proximal", "middle_intermediate", "middle_distal", "middle_tip",
            "ring_metacarpal", "ring_proximal", "ring_intermediate", "ring_distal", "ring_tip",
            "little_metacarpal", "little_proximal", "little_intermediate", "little_distal", "little_tip",
        };

        public static readonly string[] FingerNames = { "thumb", "index", "middle", "ring", "little" };

        /// <summary>Parses one message from the service. Unknown fields are ignored; a message
        /// of an unknown type, or with a missing or malformed field, raises ProtocolException.</summary>
        public static ServiceMessage Parse(string json)
        {
            JObject o;
            try { o = JObject.Parse(json); }
            catch (Exception e) { throw new ProtocolException("not a JSON object: " + e.Message); }
            var type = Str(o, "type");
            switch (type)
            {
                case "frame": return ParseFrame(o);
                case "gesture":
                    return new GestureEvent
                    {
                        T = Num(o, "t"), Gesture = Str(o, "gesture"), Event = Str(o, "event"),
                        Confidence = Num(o, "confidence"), Ray = OptRay(o["ray"])
                    };
                case "error":
                    return new ErrorMessage { Code = Str(o, "code"), Detail = Str(o, "detail") };
                case "hello":
                    return new ServerHello
                    {
                        Protocol = (int)Num(o, "protocol"), Server = OptStr(o, "server"), Session = OptStr(o, "session")
                    };
                default:
                    throw new ProtocolException("unknown message type '" + type + "'");
            }
        }

        static Frame ParseFrame(JObject o)
        {
            var f = new Frame { T = Num(o, "t"), Seq = (long)Num(o, "seq"), Hand = Str(o, "hand") };
            foreach (var p in Obj(o, "fingers").Properties())
            {
                var a = p.Value as JObject;
                if (a == null) throw new ProtocolException("fingers." + p.Name + " is not an object");
                var i = Array.IndexOf(FingerNames, p.Name);
                if (i < 0) continue;                                  // unknown names are ignored
                f.Fingers[i] = new FingerAngles
                {
                    Mcp = Num(a, "mcp"), Pip = OptNum(a, "pip"), Dip = OptNum(a, "dip"), Ip = OptNum(a, "ip"),
                    Mode = OptStr(a, "mode")
                };
            }
            foreach (var p in Obj(o, "joints").Properties())
            {
                var j = p.Value as JObject;
                if (j == null) throw new ProtocolException("joints." + p.Name + " is not an object");
                var i = Array.IndexOf(JointNames, p.Name);
                if (i < 0) continue;
                var tracked = j["tracked"];
                if (tracked != null && tracked.Type != JTokenType.Boolean)
                    throw new ProtocolException(p.Name + ".tracked: expected true or false");
                f.Joints[i] = new JointPose
                {
                    Position = V3(j["position"], p.Name), Orientation = Q(j["orientation"], p.Name),
                    Radius = OptNum(j, "radius"), Tracked = tracked == null || (bool)tracked
                };
                f.JointPresent |= 1 << i;
            }
            f.Status = o["status"] as JObject;
            if (f.Status != null) f.Optics = OptStr(f.Status, "optics");
            var g = o["gesture"] as JObject;
            if (g != null)
            {
                var active = g["active"];
                f.ActiveGesture = active == null || active.Type == JTokenType.Null ? null : (string)active;
                f.GrabStrength = OptNum(g, "grab_strength");
                f.PinchStrength = OptNum(g, "pinch_strength");
                f.PointingRay = OptRay(g["ray"]);
            }
            return f;
        }

        static Ray OptRay(JToken t)
        {
            var r = t as JObject;
            if (r == null) return null;
            return new Ray { Origin = V3(r["origin"], "ray.origin"), Direction = V3(r["direction"], "ray.direction") };
        }

        static Vec3 V3(JToken t, string what)
        {
            var a = t as JArray;
            if (a == null || a.Count != 3) throw new ProtocolException(what + ": expected 3 numbers");
            return new Vec3(Finite(a[0], what), Finite(a[1], what), Finite(a[2], what));
        }

        static Quat Q(JToken t, string what)
        {
            var a = t as JArray;
            if (a == null || a.Count != 4) throw new ProtocolException(what + ": expected a quaternion [x, y, z, w]");
            return new Quat(Finite(a[0], what), Finite(a[1], what), Finite(a[2], what), Finite(a[3], what));
        }

        static double Finite(JToken t, string what)
        {
            if (t == null || (t.Type != JTokenType.Float && t.Type != JTokenType.Integer))
                throw new ProtocolException(what + ": expected a number");
            var v = (double)t;
            if (double.IsNaN(v) || double.IsInfinity(v)) throw new ProtocolException(what + ": not finite");
            return v;
        }

        static JObject Obj(JObject o, string name)
        {
            var v = o[name] as JObject;
            if (v == null) throw new ProtocolException("missing object '" + name + "'");
            return v;
        }

        static string Str(JObject o, string name)
        {
            var v = o[name];
            if (v == null || v.Type != JTokenType.String) throw new ProtocolException("missing text field '" + name + "'");
            return (string)v;
        }

        static string OptStr(JObject o, string name)
        {
            var v = o[name];
            return v != null && v.Type == JTokenType.String ? (string)v : null;
        }

        static double Num(JObject o, string name)
        {
            if (o[name] == null) throw new ProtocolException("missing number '" + name + "'");
            return Finite(o[name], name);
        }

        static double OptNum(JObject o, string name)
        {
            return o[name] == null || o[name].Type == JTokenType.Null ? double.NaN : Finite(o[name], name);
        }
    }
}
