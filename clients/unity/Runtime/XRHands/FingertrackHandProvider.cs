// An XR Hands provider (com.unity.xr.hands 1.1 or newer): the two hand streams of a fingertrack
// service become XRHandSubsystem's left and right hands, so XR Interaction Toolkit hand interaction,
// XR Hands' gesture tools and hand visualisers use them unchanged. The assembly is compiled only
// when the XR Hands package is installed (FINGERTRACK_XR_HANDS, set by the asmdef's versionDefines).
//
// Joints: the service sends the 26 XR_EXT_hand_tracking joints in XrHandJointEXT order (palm, wrist,
// ...); XRHandJointID puts the wrist first and the palm second, the rest in the same order. Poses are
// converted to Unity's frame as the Unity OpenXR plugin converts OpenXR poses (Z mirrored), in the
// session space of the XR Origin (the service's stage space). A tracked joint gets Pose |
// HighFidelityPose (and Radius when sent); a joint the service marks untracked (held or inferred)
// gets Pose without HighFidelityPose. The root pose is the wrist's (XRHand.rootPose). A hand is
// reported (root pose and joints updated) while its stream is fresh: not past its newest frame by
// more than StaleAfterS.
#if FINGERTRACK_XR_HANDS
using System;
using Unity.Collections;
using UnityEngine;
using UnityEngine.XR.Hands;
using UnityEngine.XR.Hands.ProviderImplementation;

namespace Fingertrack.XRHands
{
    /// <summary>Where the provider takes its hands from (set by FingertrackXRHands or by code).</summary>
    public static class FingertrackHandFeed
    {
        public static IHandSource Left, Right;
        /// <summary>The render clock, s on the client's monotonic clock.</summary>
        public static Func<double> Clock = () => FingertrackClient.Now;
        /// <summary>A hand whose newest frame is older than this at the render time is not tracked, s.</summary>
        public static double StaleAfterS = 0.25;
    }

    public class FingertrackHandProvider : XRHandSubsystemProvider
    {
        public const string Id = "fingertrack-hands";

        readonly HandSample left = new HandSample(), right = new HandSample();

        public override void Start() { }
        public override void Stop() { }
        public override void Destroy() { }

        /// <summary>All 26 joints are in the layout.</summary>
        public override void GetHandLayout(NativeArray<bool> handJointsInLayout)
        {
            for (var i = 0; i < handJointsInLayout.Length; i++) handJointsInLayout[i] = true;
        }

        public override XRHandSubsystem.UpdateSuccessFlags TryUpdateHands(
            XRHandSubsystem.UpdateType updateType,
            ref Pose leftHandRootPose,
            NativeArray<XRHandJoint> leftHandJoints,
            ref Pose rightHandRootPose,
            NativeArray<XRHandJoint> rightHandJoints)
        {
            var now = FingertrackHandFeed.Clock();
            var flags = XRHandSubsystem.UpdateSuccessFlags.None;
            if (Fill(FingertrackHandFeed.Left, now, Handedness.Left, left, ref leftHandRootPose, leftHandJoints))
                flags |= XRHandSubsystem.UpdateSuccessFlags.LeftHandRootPose | XRHandSubsystem.UpdateSuccessFlags.LeftHandJoints;
            if (Fill(FingertrackHandFeed.Right, now, Handedness.Right, right, ref rightHandRootPose, rightHandJoints))
                flags |= XRHandSubsystem.UpdateSuccessFlags.RightHandRootPose | XRHandSubsystem.UpdateSuccessFlags.RightHandJoints;
            return flags;
        }

        /// <summary>XRHandJointID index (wrist 0, palm 1, ...) to the service's joint index (palm 0, wrist 1, ...).</summary>
        public static int ServiceJointIndex(int xrHandsIndex)
        {
            return xrHandsIndex == 0 ? 1 : xrHandsIndex == 1 ? 0 : xrHandsIndex;
        }

        static bool Fill(IHandSource source, double now, Handedness handedness, HandSample sample,
                         ref Pose root, NativeArray<XRHandJoint> joints)
        {
            if (source == null || !source.Sample(now, sample)) return false;
            if (sample.Newest != null && sample.SourceT - sample.Newest.T > FingertrackHandFeed.StaleAfterS) return false;
            var count = Math.Min(joints.Length, Protocol.JointCount);
            for (var i = 0; i < count; i++)
            {
                var k = ServiceJointIndex(i);
                var id = XRHandJointIDUtility.FromIndex(i);
                if ((sample.JointPresent & (1 << k)) == 0)
                {
                    joints[i] = XRHandProviderUtility.CreateJoint(handedness, XRHandJointTrackingState.None, id, Pose.identity);
                    continue;
                }
                var pose = ToUnity(sample.Positions[k], sample.Orientations[k]);
                var state = XRHandJointTrackingState.Pose;
                if (sample.Tracked[k]) state |= XRHandJointTrackingState.HighFidelityPose;
                var radius = sample.Radii[k];
                var hasRadius = !double.IsNaN(radius);
                if (hasRadius) state |= XRHandJointTrackingState.Radius;
                joints[i] = XRHandProviderUtility.CreateJoint(handedness, state, id, pose, hasRadius ? (float)radius : 0f);
            }
            const int wrist = 1;
            if ((sample.JointPresent & (1 << wrist)) == 0) return false;
            root = ToUnity(sample.Positions[wrist], sample.Orientations[wrist]);
            return true;
        }

        static Pose ToUnity(Vec3 p, Quat q)
        {
            var u = p.ToUnity();
            var r = q.ToUnity();
            return new Pose(new Vector3((float)u.X, (float)u.Y, (float)u.Z),
                            new Quaternion((float)r.X, (float)r.Y, (float)r.Z, (float)r.W));
        }
    }

    /// <summary>The XRHandSubsystem fed by FingertrackHandProvider (registered at start-up).</summary>
    public class FingertrackHandSubsystem : XRHandSubsystem
    {
        [RuntimeInitializeOnLoadMethod(RuntimeInitializeLoadType.SubsystemRegistration)]
        static void RegisterDescriptor()
        {
            XRHandSubsystemDescriptor.Register(new XRHandSubsystemDescriptor.Cinfo
            {
                id = FingertrackHandProvider.Id,
                providerType = typeof(FingertrackHandProvider),
                subsystemTypeOverride = typeof(FingertrackHandSubsystem),
            });
        }
    }
}
#endif
