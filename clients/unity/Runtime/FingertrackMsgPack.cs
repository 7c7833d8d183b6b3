// fingertrack protocol v1 in its MessagePack encoding (WebSocket subprotocol "fingertrack.msgpack"):
// the same objects as the JSON messages, read straight from the received bytes. Allocation-light
// on purpose: a frame costs its Frame object (26 joint poses in one array, five FingerAngles) and
// nothing else; keys are compared as bytes, known text values (hand, modes, gesture names, optics)
// come from constant tables, numbers never become strings. The MessagePack format is the one in
// https://github.com/msgpack/msgpack/blob/master/spec.md (only what the service sends is read;
// other types are skipped where a value is not needed and refused where it is).
using System;
using System.Text;

namespace Fingertrack
{
    /// <summary>A forward-only MessagePack reader over a byte range (no copies, no allocation).</summary>
    public struct MsgPackReader
    {
        readonly byte[] buf;
        readonly int end;
        public int Position;

        public MsgPackReader(byte[] buffer, int offset, int count)
        {
            buf = buffer; Position = offset; end = offset + count;
        }

        byte Next()
        {
            if (Position >= end) throw new ProtocolException("MessagePack message ends early");
            return buf[Position++];
        }

        ulong BigEndian(int n)
        {
            if (Position + n > end) throw new ProtocolException("MessagePack message ends early");
            ulong v = 0;
            for (var i = 0; i < n; i++) v = (v << 8) | buf[Position++];
            return v;
        }

        public bool PeekNil() { return Position < end && buf[Position] == 0xc0; }

        /// <summary>Reads a map header; -1 when the value is not a map (it is then left unread).</summary>
        public int TryReadMapHeader()
        {
            if (Position >= end) throw new ProtocolException("MessagePack message ends early");
            var b = buf[Position];
            if (b >= 0x80 && b <= 0x8f) { Position++; return b & 0x0f; }
            if (b == 0xde) { Position++; return (int)BigEndian(2); }
            if (b == 0xdf) { Position++; return Length(BigEndian(4)); }
            return -1;
        }

        public int ReadMapHeader(string what, string field = null)
        {
            var n = TryReadMapHeader();
            if (n < 0) throw new ProtocolException(Name(what, field) + ": expected an object");
            return n;
        }

        /// <summary>A field's name for an error message, joined only when one is thrown (no allocation otherwise).</summary>
        static string Name(string what, string field) { return field == null ? what : what + "." + field; }

        public int ReadArrayHeader(string what)
        {
            var b = Next();
            if (b >= 0x90 && b <= 0x9f) return b & 0x0f;
            if (b == 0xdc) return (int)BigEndian(2);
            if (b == 0xdd) return Length(BigEndian(4));
            Position--;
            throw new ProtocolException(what + ": expected an array");
        }

        static int Length(ulong n)
        {
            if (n > int.MaxValue) throw new ProtocolException("MessagePack length too large");
            return (int)n;
        }

        /// <summary>A string's bytes as (start, length) in the buffer; false when the value is not a string.</summary>
        public bool TryReadStringSpan(out int start, out int length)
        {
            start = length = 0;
            if (Position >= end) throw new ProtocolException("MessagePack message ends early");
            var b = buf[Position];
            if (b >= 0xa0 && b <= 0xbf) { Position++; length = b & 0x1f; }
            else if (b == 0xd9) { Position++; length = (int)BigEndian(1); }
            else if (b == 0xda) { Position++; length = (int)BigEndian(2); }
            else if (b == 0xdb) { Position++; length = Length(BigEndian(4)); }
            else return false;
            if (Position + length > end) throw new ProtocolException("MessagePack message ends early");
            start = Position;
            Position += length;
            return true;
        }

        /// <summary>Index of the string value in names (compared as UTF-8 bytes), -1 if it is another string.</summary>
        public int ReadName(byte[][] names, string what)
        {
            int start, length;
            if (!TryReadStringSpan(out start, out length)) throw new ProtocolException(what + ": expected text");
            return Match(start, length, names);
        }

        public int Match(int start, int length, byte[][] names)
        {
            for (var k = 0; k < names.Length; k++)
            {
                var name = names[k];
                if (name.Length != length) continue;
                var same = true;
                for (var i = 0; i < length && same; i++) same = buf[start + i] == name[i];
                if (same) return k;
            }
            return -1;
        }

        public string Decode(int start, int length) { return Encoding.UTF8.GetString(buf, start, length); }

        /// <summary>A text value: from the table when it is one of names (no allocation), else decoded.</summary>
        public string ReadText(string[] names, byte[][] utf8, string what)
        {
            int start, length;
            if (!TryReadStringSpan(out start, out length)) throw new ProtocolException(what + ": expected text");
            var k = Match(start, length, utf8);
            return k >= 0 ? names[k] : Decode(start, length);
        }

        public bool ReadBool(string what, string field = null)
        {
            var b = Next();
            if (b == 0xc3) return true;
            if (b == 0xc2) return false;
            Position--;
            throw new ProtocolException(Name(what, field) + ": expected true or false");
        }

        /// <summary>Any MessagePack number as a finite double.</summary>
        public double ReadNumber(string what, string field = null)
        {
            var b = Next();
            double v;
            if (b <= 0x7f) v = b;
            else if (b >= 0xe0) v = (sbyte)b;
            else switch (b)
            {
                case 0xca:
                {
                    var bits = (int)BigEndian(4);
                    v = BitConverter.ToSingle(BitConverter.GetBytes(bits), 0);
                    break;
                }
                case 0xcb: v = BitConverter.Int64BitsToDouble((long)BigEndian(8)); break;
                case 0xcc: v = BigEndian(1); break;
                case 0xcd: v = BigEndian(2); break;
                case 0xce: v = BigEndian(4); break;
                case 0xcf: v = BigEndian(8); break;
                case 0xd0: v = (sbyte)BigEndian(1); break;
                case 0xd1: v = (short)BigEndian(2); break;
                case 0xd2: v = (int)BigEndian(4); break;
                case 0xd3: v = (long)BigEndian(8); break;
                default:
                    Position--;
                    throw new ProtocolException(Name(what, field) + ": expected a number");
            }
            if (double.IsNaN(v) || double.IsInfinity(v)) throw new ProtocolException(Name(what, field) + ": not finite");
            return v;
        }

        /// <summary>Skips one value of any type (nested maps and arrays included).</summary>
        public void Skip()
        {
            var b = Next();
            if (b <= 0x7f || b >= 0xe0 || b == 0xc0 || b == 0xc2 || b == 0xc3) return;
            if (b >= 0x80 && b <= 0x8f) { SkipValues(2 * (b & 0x0f)); return; }
            if (b >= 0x90 && b <= 0x9f) { SkipValues(b & 0x0f); return; }
            if (b >= 0xa0 && b <= 0xbf) { Advance(b & 0x1f); return; }
            switch (b)
            {
                case 0xc4: case 0xd9: Advance((int)BigEndian(1)); return;
                case 0xc5: case 0xda: Advance((int)BigEndian(2)); return;
                case 0xc6: case 0xdb: Advance(Length(BigEndian(4))); return;
                case 0xc7: Advance((int)BigEndian(1) + 1); return;
                case 0xc8: Advance((int)BigEndian(2) + 1); return;
                case 0xc9: Advance(Length(BigEndian(4)) + 1); return;
                case 0xca: Advance(4); return;
                case 0xcb: Advance(8); return;
                case 0xcc: case 0xd0: Advance(1); return;
                case 0xcd: case 0xd1: Advance(2); return;
                case 0xce: case 0xd2: Advance(4); return;
                case 0xcf: case 0xd3: Advance(8); return;
                case 0xd4: Advance(2); return;
                case 0xd5: Advance(3); return;
                case 0xd6: Advance(5); return;
                case 0xd7: Advance(9); return;
                case 0xd8: Advance(17); return;
                case 0xdc: SkipValues((int)BigEndian(2)); return;
                case 0xdd: SkipValues(Length(BigEndian(4))); return;
                case 0xde: SkipValues(2 * (int)BigEndian(2)); return;
                case 0xdf: SkipValues(2 * Length(BigEndian(4))); return;
                default: throw new ProtocolException("not MessagePack (byte 0xc1)");
            }
        }

        void SkipValues(int n) { for (var i = 0; i < n; i++) Skip(); }

        void Advance(int n)
        {
            if (n < 0 || Position + n > end) throw new ProtocolException("MessagePack message ends early");
            Position += n;
        }
    }

    public static partial class MsgPackProtocol
    {
        static byte[][] Utf8(string[] names)
        {
            var r = new byte[names.Length][];
            for (var i = 0; i < names.Length; i++) r[i] = Encoding.UTF8.GetBytes(names[i]);
            return r;
        }

        static readonly string[] TopKeys = { "type", "t", "seq", "hand", "fingers", "joints", "status", "gesture",
                                             "confidence", "ray", "event", "code", "detail", "protocol", "server", "session" };
        const int KType = 0, KT = 1, KSeq = 2, KHand = 3, KFingers = 4, KJoints = 5, KStatus = 6, KGesture = 7,
                  KConfidence = 8, KRay = 9, KEvent = 10, KCode = 11, KDetail = 12, KProtocol = 13, KServer = 14, KSession = 15;
        static readonly byte[][] TopKeysUtf8 = Utf8(TopKeys);

        static readonly string[] Types = { "frame", "gesture", "error", "hello" };
        static readonly byte[][] TypesUtf8 = Utf8(Types);
        static readonly string[] Hands = { "right", "left" };
        static readonly byte[][] HandsUtf8 = Utf8(Hands);
        static readonly byte[][] FingersUtf8 = Utf8(Protocol.FingerNames);
        static readonly byte[][] JointsUtf8 = Utf8(Protocol.JointNames);
        static readonly string[] AngleKeys = { "mcp", "pip", "dip", "ip", "mode" };
        static readonly byte[][] AngleKeysUtf8 = Utf8(AngleKeys);
        static readonly string[] Modes = { "slow", "fast", "fused", "none" };
        static readonly byte[][] ModesUtf8 = Utf8(Modes);
        static readonly string[] JointKeys = { "position", "orientation", "radius", "tracked" };
        static readonly byte[][] JointKeysUtf8 = Utf8(JointKeys);
        static readonly string[] OpticsKey = { "optics" };
        static readonly byte[][] OpticsKeyUtf8 = Utf8(OpticsKey);
        static readonly string[] OpticsValues = { "tracking", "occluded", "waiting" };
        static readonly byte[][] OpticsValuesUtf8 = Utf8(OpticsValues);
        static readonly string[] GestureKeys = { "active", "grab_strength", "pinch_strength", "ray" };
        static readonly byte[][] GestureKeysUtf8 = Utf8(GestureKeys);
        static readonly string[] GestureNames = { "point", "grasp", "pinch", "open" };
        static readonly byte[][] GestureNamesUtf8 = Utf8(GestureNames);
        static readonly string[] EventNames = { "start", "end" };
        static readonly byte[][] EventNamesUtf8 = Utf8(EventNames);
        static readonly string[] RayKeys = { "origin", "direction" };
        static readonly byte[][] RayKeysUtf8 = Utf8(RayKeys);

        /// <summary>Parses one binary message from the service (same rules as Protocol.Parse).</summary>
        public static ServiceMessage Parse(byte[] data, int offset, int count)
        {
            var r = new MsgPackReader(data, offset, count);
            var n = r.TryReadMapHeader();
            if (n < 0) throw new ProtocolException("not a MessagePack map");
            var fieldsAt = r.Position;
            // the type first (any key order is allowed): one pass over the keys, values skipped
            var type = -1;
            for (var i = 0; i < n; i++)
            {
                int start, length;
                if (!r.TryReadStringSpan(out start, out length)) { r.Skip(); r.Skip(); continue; }
                if (r.Match(start, length, TopKeysUtf8) == KType)
                {
                    int ts, tl;
                    if (!r.TryReadStringSpan(out ts, out tl)) throw new ProtocolException("missing text field 'type'");
                    type = r.Match(ts, tl, TypesUtf8);
                    if (type < 0) throw new ProtocolException("unknown message type '" + r.Decode(ts, tl) + "'");
                    break;
                }
                r.Skip();
            }
            if (type < 0) throw new ProtocolException("missing text field 'type'");
            r.Position = fieldsAt;
            switch (type)
            {
                case 0: return ReadFrame(ref r, n);
                case 1: return ReadGesture(ref r, n);
                case 2: return ReadError(ref r, n);
                default: return ReadHello(ref r, n);
            }
        }

        static Frame ReadFrame(ref MsgPackReader r, int n)
        {
            var f = new Frame();
            bool hasT = false, hasSeq = false, hasFingers = false, hasJoints = false;
            for (var i = 0; i < n; i++)
            {
                int start, length;
                if (!r.TryReadStringSpan(out start, out length)) { r.Skip(); r.Skip(); continue; }
                switch (r.Match(start, length, TopKeysUtf8))
                {
                    case KT: f.T = r.ReadNumber("t"); hasT = true; break;
                    case KSeq: f.Seq = (long)r.ReadNumber("seq"); hasSeq = true; break;
                    case KHand: f.Hand = r.ReadText(Hands, HandsUtf8, "hand"); break;
                    case KFingers: ReadFingers(ref r, f); hasFingers = true; break;
                    case KJoints: ReadJoints(ref r, f); hasJoints = true; break;
                    case KStatus: ReadStatus(ref r, f); break;
                    case KGesture: ReadGestureValues(ref r, f); break;
                    default: r.Skip(); break;
                }
            }
            if (!hasT) throw new ProtocolException("missing number 't'");
            if (!hasSeq) throw new ProtocolException("missing number 'seq'");
            if (f.Hand == null) throw new ProtocolException("missing text field 'hand'");
            if (!hasFingers) throw new ProtocolException("missing object 'fingers'");
            if (!hasJoints) throw new ProtocolException("missing object 'joints'");
            return f;
        }

        static void ReadFingers(ref MsgPackReader r, Frame f)
        {
            var n = r.ReadMapHeader("fingers");
            for (var i = 0; i < n; i++)
            {
                var finger = r.ReadName(FingersUtf8, "fingers");
                if (finger < 0) { r.Skip(); continue; }
                var m = r.ReadMapHeader("fingers", Protocol.FingerNames[finger]);
                var a = new FingerAngles { Pip = double.NaN, Dip = double.NaN, Ip = double.NaN, Mcp = double.NaN };
                var hasMcp = false;
                for (var k = 0; k < m; k++)
                {
                    var key = r.ReadName(AngleKeysUtf8, "fingers key");
                    switch (key)
                    {
                        case 0: a.Mcp = r.ReadNumber("mcp"); hasMcp = true; break;
                        case 1: a.Pip = NumberOrNaN(ref r, "pip"); break;
                        case 2: a.Dip = NumberOrNaN(ref r, "dip"); break;
                        case 3: a.Ip = NumberOrNaN(ref r, "ip"); break;
                        case 4: a.Mode = r.PeekNil() ? SkipNil(ref r) : r.ReadText(Modes, ModesUtf8, "mode"); break;
                        default: r.Skip(); break;
                    }
                }
                if (!hasMcp) throw new ProtocolException("missing number 'mcp'");
                f.Fingers[finger] = a;
            }
        }

        static string SkipNil(ref MsgPackReader r) { r.Skip(); return null; }

        static double NumberOrNaN(ref MsgPackReader r, string what, string field = null)
        {
            if (r.PeekNil()) { r.Skip(); return double.NaN; }
            return r.ReadNumber(what, field);
        }

        static void ReadJoints(ref MsgPackReader r, Frame f)
        {
            var n = r.ReadMapHeader("joints");
            for (var i = 0; i < n; i++)
            {
                var joint = r.ReadName(JointsUtf8, "joints");
                if (joint < 0) { r.Skip(); continue; }
                var name = Protocol.JointNames[joint];
                var m = r.ReadMapHeader("joints", name);
                var pose = new JointPose { Radius = double.NaN, Tracked = true };
                bool hasPosition = false, hasOrientation = false;
                for (var k = 0; k < m; k++)
                {
                    switch (r.ReadName(JointKeysUtf8, name))
                    {
                        case 0: pose.Position = ReadVec3(ref r, name); hasPosition = true; break;
                        case 1: pose.Orientation = ReadQuat(ref r, name); hasOrientation = true; break;
                        case 2: pose.Radius = NumberOrNaN(ref r, name, "radius"); break;
                        case 3: pose.Tracked = r.ReadBool(name, "tracked"); break;
                        default: r.Skip(); break;
                    }
                }
                if (!hasPosition) throw new ProtocolException(name + ": expected 3 numbers");
                if (!hasOrientation) throw new ProtocolException(name + ": expected a quaternion [x, y, z, w]");
                f.Joints[joint] = pose;
                f.JointPresent |= 1 << joint;
            }
        }

        static Vec3 ReadVec3(ref MsgPackReader r, string what)
        {
            if (r.ReadArrayHeader(what) != 3) throw new ProtocolException(what + ": expected 3 numbers");
            return new Vec3(r.ReadNumber(what), r.ReadNumber(what), r.ReadNumber(what));
        }

        static Quat ReadQuat(ref MsgPackReader r, string what)
        {
            if (r.ReadArrayHeader(what) != 4) throw new ProtocolException(what + ": expected a quaternion [x, y, z, w]");
            return new Quat(r.ReadNumber(what), r.ReadNumber(what), r.ReadNumber(what), r.ReadNumber(what));
        }

        static void ReadStatus(ref MsgPackReader r, Frame f)
        {
            var n = r.TryReadMapHeader();
            if (n < 0) { r.Skip(); return; }
            for (var i = 0; i < n; i++)
            {
                int start, length;
                if (r.TryReadStringSpan(out start, out length) && r.Match(start, length, OpticsKeyUtf8) == 0)
                    f.Optics = r.ReadText(OpticsValues, OpticsValuesUtf8, "status.optics");
                else r.Skip();
            }
        }

        static void ReadGestureValues(ref MsgPackReader r, Frame f)
        {
            var n = r.TryReadMapHeader();
            if (n < 0) { r.Skip(); return; }
            for (var i = 0; i < n; i++)
            {
                switch (r.ReadName(GestureKeysUtf8, "gesture"))
                {
                    case 0: f.ActiveGesture = r.PeekNil() ? SkipNil(ref r) : r.ReadText(GestureNames, GestureNamesUtf8, "gesture.active"); break;
                    case 1: f.GrabStrength = NumberOrNaN(ref r, "grab_strength"); break;
                    case 2: f.PinchStrength = NumberOrNaN(ref r, "pinch_strength"); break;
                    case 3: f.PointingRay = ReadRay(ref r); break;
                    default: r.Skip(); break;
                }
            }
        }

        static Ray ReadRay(ref MsgPackReader r)
        {
            var n = r.TryReadMapHeader();
            if (n < 0) { r.Skip(); return null; }
            var ray = new Ray();
            for (var i = 0; i < n; i++)
            {
                switch (r.ReadName(RayKeysUtf8, "ray"))
                {
                    case 0: ray.Origin = ReadVec3(ref r, "ray.origin"); break;
                    case 1: ray.Direction = ReadVec3(ref r, "ray.direction"); break;
                    default: r.Skip(); break;
                }
            }
            return ray;
        }

        static GestureEvent ReadGesture(ref MsgPackReader r, int n)
        {
            var g = new GestureEvent { T = double.NaN, Confidence = double.NaN };
            for (var i = 0; i < n; i++)
            {
                int start, length;
                if (!r.TryReadStringSpan(out start, out length)) { r.Skip(); r.Skip(); continue; }
                switch (r.Match(start, length, TopKeysUtf8))
                {
                    case KT: g.T = r.ReadNumber("t"); break;
                    case KGesture: g.Gesture = r.ReadText(GestureNames, GestureNamesUtf8, "gesture"); break;
                    case KEvent: g.Event = r.ReadText(EventNames, EventNamesUtf8, "event"); break;
                    case KConfidence: g.Confidence = r.ReadNumber("confidence"); break;
                    case KRay: g.Ray = ReadRay(ref r); break;
                    default: r.Skip(); break;
                }
            }
            if (double.IsNaN(g.T)) throw new ProtocolException("missing number 't'");
            if (g.Gesture == null) throw new ProtocolException("missing text field 'gesture'");
            if (g.Event == null) throw new ProtocolException("missing text field 'event'");
            if (double.IsNaN(g.Confidence)) throw new ProtocolException("missing number 'confidence'");
            return g;
        }

        static ErrorMessage ReadError(ref MsgPackReader r, int n)
        {
            var e = new ErrorMessage();
            for (var i = 0; i < n; i++)
            {
                int start, length;
                if (!r.TryReadStringSpan(out start, out length)) { r.Skip(); r.Skip(); continue; }
                var key = r.Match(start, length, TopKeysUtf8);
                if (key == KCode) e.Code = r.ReadText(Types, TypesUtf8, "code");
                else if (key == KDetail) e.Detail = r.ReadText(Types, TypesUtf8, "detail");
                else r.Skip();
            }
            if (e.Code == null) throw new ProtocolException("missing text field 'code'");
            if (e.Detail == null) throw new ProtocolException("missing text field 'detail'");
            return e;
        }

        static ServerHello ReadHello(ref MsgPackReader r, int n)
        {
            var h = new ServerHello();
            var hasProtocol = false;
            for (var i = 0; i < n; i++)
            {
                int start, length;
                if (!r.TryReadStringSpan(out start, out length)) { r.Skip(); r.Skip(); continue; }
                switch (r.Match(start, length, TopKeysUtf8))
                {
                    case KProtocol: h.Protocol = (int)r.ReadNumber("protocol"); hasProtocol = true; break;
                    case KServer: h.Server = r.ReadText(Types, TypesUtf8, "server"); break;
                    case KSession: h.Session = r.ReadText(Types, TypesUtf8, "session"); break;
                    default: r.Skip(); break;
                }
            }
            if (!hasProtocol) throw new ProtocolException("missing number 'protocol'");
            return h;
        }
    }
}
