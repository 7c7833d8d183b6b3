// Frames at the render time. Frames carry t on the source's clock (the glove's); the client stamps
// each on arrival with its own monotonic clock. The clock offset (local - source) is estimated as
// the smallest (arrival - t) over a window of recent frames: every arrival is late by a transport
// delay d >= 0, so arrival - t = offset + d, and the least-delayed frame bounds the offset most
// tightly (the minimum-delay filter of clock synchronisation, as in Cristian's algorithm and NTP's
// clock filter). The window keeps the estimate following a slowly drifting clock. A render time L
// on the client's clock is the source time L - offset - DelayS; the pose there is interpolated
// between the two frames around it: positions linearly, orientations by slerp (exact for motion at
// constant velocity and constant angular velocity about a fixed axis). After the newest frame the
// newest pose is held (no extrapolation).
using System;

namespace Fingertrack
{
    /// <summary>Local-minus-source clock offset from frame timestamps and arrival times (header comment).</summary>
    public sealed class ClockOffsetEstimator
    {
        readonly double[] samples;
        int count, next;

        /// <param name="window">number of recent frames the minimum is taken over (2.8 s at 90 Hz for 256)</param>
        public ClockOffsetEstimator(int window = 256)
        {
            if (window < 1) throw new ArgumentException("window must be at least 1 frame");
            samples = new double[window];
        }

        /// <summary>Seconds to add to a source time to get the client's time (NaN before the first frame).</summary>
        public double OffsetS { get; private set; } = double.NaN;

        public void Add(double sourceT, double arrivalS)
        {
            samples[next] = arrivalS - sourceT;
            next = (next + 1) % samples.Length;
            if (count < samples.Length) count++;
            var min = double.PositiveInfinity;
            for (var i = 0; i < count; i++) if (samples[i] < min) min = samples[i];
            OffsetS = min;
        }

        public void Reset() { count = next = 0; OffsetS = double.NaN; }
    }

    /// <summary>One hand, sampled at the client's time localS (FingertrackClient.Now); main thread.</summary>
    public interface IHandSource
    {
        bool Sample(double localS, HandSample into);
    }

    /// <summary>A hand's joints at one time, OpenXR order (Protocol.JointNames); filled in place.</summary>
    public sealed class HandSample
    {
        public readonly Vec3[] Positions = new Vec3[Protocol.JointCount];
        public readonly Quat[] Orientations = new Quat[Protocol.JointCount];
        /// <summary>Metres; NaN where the service sends no radius.</summary>
        public readonly double[] Radii = new double[Protocol.JointCount];
        public readonly bool[] Tracked = new bool[Protocol.JointCount];
        /// <summary>Bit i set: joint i has a pose.</summary>
        public int JointPresent;
        /// <summary>The source time sampled, s.</summary>
        public double SourceT;
        /// <summary>True when the render time was past the newest frame and its pose is held.</summary>
        public bool Held;
        /// <summary>The newer of the two frames used (its gesture values, status, ...).</summary>
        public Frame Newest;
    }

    /// <summary>Keeps the last frames of one hand and samples them at render times (header comment).
    /// Add on the thread that receives (or the main thread); Sample on the main thread; not thread-safe.</summary>
    public sealed class FrameInterpolator
    {
        readonly Frame[] ring;
        int count, next;
        public readonly ClockOffsetEstimator Clock;

        /// <summary>How far behind the newest data the hand is shown, s: a little more than one frame
        /// interval, so that a frame after the render time has usually arrived. Default 1.5 frames at 90 Hz.</summary>
        public double DelayS = 1.5 / 90.0;

        public FrameInterpolator(int frames = 8, int offsetWindow = 256)
        {
            if (frames < 2) throw new ArgumentException("frames must be at least 2");
            ring = new Frame[frames];
            Clock = new ClockOffsetEstimator(offsetWindow);
        }

        /// <summary>A received frame (ReceivedAtS set). Frames older than the newest are ignored.</summary>
        public void Add(Frame f)
        {
            if (double.IsNaN(f.ReceivedAtS)) throw new ArgumentException("the frame has no arrival time (ReceivedAtS)");
            if (count > 0 && f.T <= Newest.T) return;
            Clock.Add(f.T, f.ReceivedAtS);
            ring[next] = f;
            next = (next + 1) % ring.Length;
            if (count < ring.Length) count++;
        }

        public Frame Newest { get { return count == 0 ? null : ring[(next - 1 + ring.Length) % ring.Length]; } }

        Frame At(int ageFromNewest) { return ring[(next - 1 - ageFromNewest + 2 * ring.Length) % ring.Length]; }

        /// <summary>The source time shown at the client's time localS.</summary>
        public double SourceTimeAt(double localS) { return localS - Clock.OffsetS - DelayS; }

        /// <summary>Fills into with the hand at the client's time localS; false before the first frame.</summary>
        public bool Sample(double localS, HandSample into)
        {
            if (count == 0) return false;
            return SampleSource(SourceTimeAt(localS), into);
        }

        /// <summary>Fills into with the hand at source time t.</summary>
        public bool SampleSource(double t, HandSample into)
        {
            if (count == 0) return false;
            var newest = Newest;
            into.SourceT = t;
            into.Newest = newest;
            if (t >= newest.T) { Copy(newest, into); into.Held = t > newest.T; return true; }
            into.Held = false;
            var b = newest;
            for (var age = 1; age < count; age++)
            {
                var a = At(age);
                if (a.T <= t)
                {
                    Blend(a, b, (t - a.T) / (b.T - a.T), into);
                    return true;
                }
                b = a;
            }
            Copy(b, into);                           // before the oldest kept frame: the oldest
            return true;
        }

        static void Copy(Frame f, HandSample s)
        {
            s.JointPresent = f.JointPresent;
            for (var i = 0; i < Protocol.JointCount; i++)
            {
                var j = f.Joints[i];
                s.Positions[i] = j.Position; s.Orientations[i] = j.Orientation;
                s.Radii[i] = j.Radius; s.Tracked[i] = j.Tracked;
            }
        }

        static void Blend(Frame a, Frame b, double u, HandSample s)
        {
            s.JointPresent = a.JointPresent & b.JointPresent;
            for (var i = 0; i < Protocol.JointCount; i++)
            {
                JointPose ja = a.Joints[i], jb = b.Joints[i];
                s.Positions[i] = new Vec3(ja.Position.X + u * (jb.Position.X - ja.Position.X),
                                          ja.Position.Y + u * (jb.Position.Y - ja.Position.Y),
                                          ja.Position.Z + u * (jb.Position.Z - ja.Position.Z));
                s.Orientations[i] = Slerp(ja.Orientation, jb.Orientation, u);
                s.Radii[i] = ja.Radius + u * (jb.Radius - ja.Radius);
                s.Tracked[i] = ja.Tracked && jb.Tracked;
            }
        }

        /// <summary>Spherical linear interpolation along the shorter arc (Shoemake 1985).</summary>
        public static Quat Slerp(Quat a, Quat b, double u)
        {
            var dot = a.X * b.X + a.Y * b.Y + a.Z * b.Z + a.W * b.W;
            if (dot < 0) { b = new Quat(-b.X, -b.Y, -b.Z, -b.W); dot = -dot; }
            double wa, wb;
            if (dot > 0.9995)
            {
                wa = 1 - u; wb = u;                   // nearly equal: linear, then normalised
            }
            else
            {
                var theta = Math.Acos(dot);
                var sin = Math.Sin(theta);
                wa = Math.Sin((1 - u) * theta) / sin;
                wb = Math.Sin(u * theta) / sin;
            }
            var q = new Quat(wa * a.X + wb * b.X, wa * a.Y + wb * b.Y, wa * a.Z + wb * b.Z, wa * a.W + wb * b.W);
            var n = Math.Sqrt(q.X * q.X + q.Y * q.Y + q.Z * q.Z + q.W * q.W);
            return new Quat(q.X / n, q.Y / n, q.Z / n, q.W / n);
        }
    }
}
