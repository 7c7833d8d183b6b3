// API SURFACE FOR COMPILATION ONLY, NOT AN IMPLEMENTATION OF XR HANDS.
//
// The public types and signatures of Unity's XR Hands package (com.unity.xr.hands 1.5.0), as far as
// Runtime/XRHands needs them (UnityEngine's own types: UnityEngineApiSurface.cs), so
// that the provider compiles under Mono and can be driven by the tests without Unity. Names,
// namespaces, signatures, enum values and the joint-packing of XRHandProviderUtility.CreateJoint
// follow the package's source (Runtime/Enums.cs, XRHandJoint.cs, XRHandSubsystem.cs,
// XRHandSubsystemDescriptor.cs, XRHandSubsystemProvider.cs, XRHandProviderUtility.cs). Bodies are
// reduced to what a test needs: NativeArray is a managed array, SubsystemProvider has no engine
// behind it, Register records the descriptor instead of handing it to Unity's SubsystemManager.
// Nothing here ships in the package: Tests~ is hidden from Unity.
using System;
using System.Collections.Generic;

namespace Unity.Collections
{
    public enum Allocator { Invalid = 0, None = 1, Temp = 2, TempJob = 3, Persistent = 4 }

    /// <summary>Surface only: a managed array behind NativeArray's indexer and Length.</summary>
    public struct NativeArray<T> : IDisposable where T : struct
    {
        T[] items;
        public NativeArray(int length, Allocator allocator) { items = new T[length]; }
        public int Length { get { return items.Length; } }
        public T this[int index] { get { return items[index]; } set { items[index] = value; } }
        public void Dispose() { items = null; }
    }
}

namespace UnityEngine.SubsystemsImplementation
{
    public abstract class SubsystemProvider
    {
        public virtual void Start() { }
        public virtual void Stop() { }
        public virtual void Destroy() { }
    }

    public abstract class SubsystemProvider<TSubsystem> : SubsystemProvider { }

    public abstract class SubsystemWithProvider<TSubsystem, TSubsystemDescriptor, TProvider> : ISubsystem where TProvider : SubsystemProvider
    {
        protected internal TProvider provider { get; internal set; }
        public bool running { get; internal set; }
        public void Start() { running = true; }
        public void Stop() { running = false; }
        public void Destroy() { running = false; }
    }

    public abstract class SubsystemDescriptorWithProvider<TSubsystem, TProvider> : ISubsystemDescriptor
    {
        public string id { get; protected set; }
        public Type providerType { get; protected set; }
        public Type subsystemTypeOverride { get; protected set; }
        /// <summary>Surface only: the package's SubsystemManager creates the subsystem with its provider.</summary>
        public TSubsystem Create() { throw new NotSupportedException("API surface for compilation only"); }
    }
}

namespace UnityEngine.XR.Hands
{
    using Unity.Collections;
    using UnityEngine.SubsystemsImplementation;
    using UnityEngine.XR.Hands.ProviderImplementation;

    [Flags]
    public enum XRHandJointTrackingState
    {
        None = 0,
        Radius = 1 << 0,
        Pose = 1 << 1,
        LinearVelocity = 1 << 2,
        AngularVelocity = 1 << 3,
        WillNeverBeValid = 1 << 4,
        HighFidelityPose = 1 << 5,
    }

    public enum XRHandJointID
    {
        Invalid,
        BeginMarker,
        Wrist = BeginMarker,
        Palm,
        ThumbMetacarpal, ThumbProximal, ThumbDistal, ThumbTip,
        IndexMetacarpal, IndexProximal, IndexIntermediate, IndexDistal, IndexTip,
        MiddleMetacarpal, MiddleProximal, MiddleIntermediate, MiddleDistal, MiddleTip,
        RingMetacarpal, RingProximal, RingIntermediate, RingDistal, RingTip,
        LittleMetacarpal, LittleProximal, LittleIntermediate, LittleDistal, LittleTip,
        EndMarker
    }

    public enum Handedness { Invalid, Left, Right }

    public static class XRHandJointIDUtility
    {
        public static int ToIndex(this XRHandJointID jointId) { return (int)jointId - 1; }
        public static XRHandJointID FromIndex(int index) { return (XRHandJointID)(index + 1); }
    }

    public struct XRHandJoint
    {
        public XRHandJointID id { get { return (XRHandJointID)(m_IdAndHandedness & ~k_IsRightHandBit); } }
        public Handedness handedness { get { return (m_IdAndHandedness & k_IsRightHandBit) != 0 ? Handedness.Right : Handedness.Left; } }
        public XRHandJointTrackingState trackingState { get { return m_TrackingState; } }

        public bool TryGetRadius(out float radius)
        {
            if ((m_TrackingState & XRHandJointTrackingState.Radius) == XRHandJointTrackingState.None) { radius = 0f; return false; }
            radius = m_Radius;
            return true;
        }

        public bool TryGetPose(out Pose pose)
        {
            if ((m_TrackingState & XRHandJointTrackingState.Pose) == XRHandJointTrackingState.None) { pose = Pose.identity; return false; }
            pose = m_Pose;
            return true;
        }

        internal int m_IdAndHandedness;
        internal Pose m_Pose;
        internal float m_Radius;
        internal Vector3 m_LinearVelocity;
        internal Vector3 m_AngularVelocity;
        internal XRHandJointTrackingState m_TrackingState;
        internal const int k_IsRightHandBit = 1 << 31;
    }

    public class XRHandSubsystem : SubsystemWithProvider<XRHandSubsystem, XRHandSubsystemDescriptor, XRHandSubsystemProvider>
    {
        [Flags]
        public enum UpdateSuccessFlags
        {
            None = 0,
            LeftHandRootPose = 1 << 0,
            LeftHandJoints = 1 << 1,
            RightHandRootPose = 1 << 2,
            RightHandJoints = 1 << 3,
            All = LeftHandRootPose | LeftHandJoints | RightHandRootPose | RightHandJoints
        }

        public enum UpdateType { Dynamic, BeforeRender }
    }

    public class XRHandSubsystemDescriptor : SubsystemDescriptorWithProvider<XRHandSubsystem, XRHandSubsystemProvider>
    {
        public struct Cinfo
        {
            public string id { get; set; }
            public Type providerType { get; set; }
            public Type subsystemTypeOverride { get; set; }
            public bool supportsAimPose { get; set; }
            public bool supportsAimActivateValue { get; set; }
            public bool supportsGraspValue { get; set; }
            public bool supportsGripPose { get; set; }
            public bool supportsPinchPose { get; set; }
            public bool supportsPinchValue { get; set; }
            public bool supportsPokePose { get; set; }
        }

        XRHandSubsystemDescriptor(Cinfo cinfo)
        {
            id = cinfo.id; providerType = cinfo.providerType; subsystemTypeOverride = cinfo.subsystemTypeOverride;
        }

        /// <summary>Surface only: records the descriptor (the package hands it to SubsystemManager).</summary>
        public static readonly List<XRHandSubsystemDescriptor> RegisteredForTests = new List<XRHandSubsystemDescriptor>();

        public static void Register(Cinfo cinfo) { RegisteredForTests.Add(new XRHandSubsystemDescriptor(cinfo)); }
    }
}

namespace UnityEngine.XR.Hands.ProviderImplementation
{
    using Unity.Collections;
    using UnityEngine.SubsystemsImplementation;

    public abstract class XRHandSubsystemProvider : SubsystemProvider<XRHandSubsystem>
    {
        public abstract void GetHandLayout(NativeArray<bool> handJointsInLayout);

        public abstract XRHandSubsystem.UpdateSuccessFlags TryUpdateHands(
            XRHandSubsystem.UpdateType updateType,
            ref Pose leftHandRootPose,
            NativeArray<XRHandJoint> leftHandJoints,
            ref Pose rightHandRootPose,
            NativeArray<XRHandJoint> rightHandJoints);
    }

    public static partial class XRHandProviderUtility
    {
        public static XRHandJoint CreateJoint(
            Handedness handedness,
            XRHandJointTrackingState trackingState,
            XRHandJointID id,
            Pose pose,
            float radius = 0f,
            Vector3 linearVelocity = new Vector3(),
            Vector3 angularVelocity = new Vector3())
        {
            // surface only: the joint packs its id with a right-hand bit, as the package's XRHandJoint reads it back
            var joint = new XRHandJoint();
            joint.m_IdAndHandedness = (int)id | (handedness == Handedness.Right ? XRHandJoint.k_IsRightHandBit : 0);
            joint.m_TrackingState = trackingState;
            joint.m_Pose = pose;
            joint.m_Radius = radius;
            joint.m_LinearVelocity = linearVelocity;
            joint.m_AngularVelocity = angularVelocity;
            return joint;
        }

        public class SubsystemUpdater
        {
            public SubsystemUpdater(XRHandSubsystem subsystem) { }
            public void Start() { }
            public void Stop() { }
            public void Destroy() { }
        }
    }
}
