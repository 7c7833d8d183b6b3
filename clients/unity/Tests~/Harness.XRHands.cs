// The XR Hands provider driven as XRHandSubsystem drives it (TryUpdateHands with the two hands'
// joint arrays), against the API surface in XRHandsApiSurface.cs. Frames of two MessagePack files
// (left, right) are stamped as received 100 s after their source time; update k runs at the render
// time where the source time shown is frame k's, so each update must write that frame's joints.
using System;
using System.Reflection;
using Fingertrack;
using Fingertrack.XRHands;
using Newtonsoft.Json.Linq;
using Unity.Collections;
using UnityEngine;
using UnityEngine.XR.Hands;

static partial class Harness
{
    sealed class ListSource : IHandSource
    {
        public readonly FrameInterpolator Interpolator = new FrameInterpolator(frames: 4);
        public bool Sample(double localS, HandSample into) { return Interpolator.Sample(localS, into); }
    }

    static JObject DescribeJoints(NativeArray<XRHandJoint> joints, Pose root)
    {
        var list = new JArray();
        for (var i = 0; i < joints.Length; i++)
        {
            var j = joints[i];
            Pose p;
            var hasPose = j.TryGetPose(out p);
            float r;
            var hasRadius = j.TryGetRadius(out r);
            list.Add(new JObject {
                { "id", j.id.ToString() }, { "index", i }, { "handedness", j.handedness.ToString() }, { "state", (int)j.trackingState },
                { "position", hasPose ? new JArray(p.position.x, p.position.y, p.position.z) : null },
                { "rotation", hasPose ? new JArray(p.rotation.x, p.rotation.y, p.rotation.z, p.rotation.w) : null },
                { "radius", hasRadius ? (JToken)r : null } });
        }
        return new JObject { { "root", new JArray(root.position.x, root.position.y, root.position.z,
                                                  root.rotation.x, root.rotation.y, root.rotation.z, root.rotation.w) },
                             { "joints", list } };
    }

    static int XRHands(string leftPath, string rightPath)
    {
        // registration as Unity does it at start-up: every [RuntimeInitializeOnLoadMethod(SubsystemRegistration)]
        foreach (var type in typeof(FingertrackHandProvider).Assembly.GetTypes())
            foreach (var m in type.GetMethods(BindingFlags.Static | BindingFlags.NonPublic | BindingFlags.Public))
            {
                var a = m.GetCustomAttribute<RuntimeInitializeOnLoadMethodAttribute>();
                if (a != null && a.loadType == RuntimeInitializeLoadType.SubsystemRegistration) m.Invoke(null, null);
            }
        var registered = new JArray();
        foreach (var d in XRHandSubsystemDescriptor.RegisteredForTests)
            registered.Add(new JObject { { "id", d.id }, { "provider", d.providerType.FullName },
                                         { "subsystem", d.subsystemTypeOverride != null ? d.subsystemTypeOverride.FullName : null } });
        Print(new JObject { { "registered", registered } });

        var provider = (FingertrackHandProvider)Activator.CreateInstance(XRHandSubsystemDescriptor.RegisteredForTests[0].providerType);
        var count = XRHandJointID.EndMarker.ToIndex();
        var layout = new NativeArray<bool>(count, Allocator.Persistent);
        provider.GetHandLayout(layout);
        var inLayout = 0;
        for (var i = 0; i < count; i++) if (layout[i]) inLayout++;
        Print(new JObject { { "layout", inLayout } });
        provider.Start();

        var left = new ListSource();
        var right = new ListSource();
        FingertrackHandFeed.Left = left;
        FingertrackHandFeed.Right = right;
        var leftFrames = ReadFramed(leftPath);
        var rightFrames = ReadFramed(rightPath);
        var leftJoints = new NativeArray<XRHandJoint>(count, Allocator.Persistent);
        var rightJoints = new NativeArray<XRHandJoint>(count, Allocator.Persistent);
        const double arrivalDelay = 100.0;
        for (var k = 0; k < Math.Max(leftFrames.Count, rightFrames.Count); k++)
        {
            double t = double.NaN;
            if (k < leftFrames.Count) t = Feed(left, leftFrames[k], arrivalDelay);
            if (k < rightFrames.Count) t = Feed(right, rightFrames[k], arrivalDelay);
            var render = t + arrivalDelay + left.Interpolator.DelayS;
            FingertrackHandFeed.Clock = () => render;
            Pose leftRoot = Pose.identity, rightRoot = Pose.identity;
            var flags = provider.TryUpdateHands(XRHandSubsystem.UpdateType.Dynamic, ref leftRoot, leftJoints, ref rightRoot, rightJoints);
            Print(new JObject { { "update", k }, { "t", t }, { "flags", (int)flags },
                                { "left", DescribeJoints(leftJoints, leftRoot) }, { "right", DescribeJoints(rightJoints, rightRoot) } });
        }
        // the stream stops: a render time past the newest frame by more than StaleAfterS reports no hand
        var last = FingertrackHandFeed.Clock();
        FingertrackHandFeed.Clock = () => last + FingertrackHandFeed.StaleAfterS + 0.1;
        Pose l2 = Pose.identity, r2 = Pose.identity;
        Print(new JObject { { "stale_flags", (int)provider.TryUpdateHands(XRHandSubsystem.UpdateType.BeforeRender, ref l2, leftJoints, ref r2, rightJoints) } });
        provider.Stop();
        provider.Destroy();
        return 0;
    }

    static double Feed(ListSource source, ArraySegment<byte> message, double arrivalDelay)
    {
        var f = (Frame)MsgPackProtocol.Parse(message.Array, message.Offset, message.Count);
        f.ReceivedAtS = f.T + arrivalDelay;
        source.Interpolator.Add(f);
        return f.T;
    }
}
