// Unity component: subscribes to the left and right hand sessions of a fingertrack service and runs
// the XR Hands subsystem fed by them (FingertrackHandProvider), updated by XR Hands' own
// SubsystemUpdater at EarlyUpdate.XRUpdate and before render. Put one in the scene instead of (or
// with no other) hand-tracking provider; XRI hand interaction and XR Hands visualisers then find
// the hands through SubsystemManager as usual. Compiled only inside Unity with XR Hands installed.
#if FINGERTRACK_XR_HANDS && UNITY_5_3_OR_NEWER
using System.Collections.Generic;
using UnityEngine;
using UnityEngine.Events;
using UnityEngine.XR.Hands;
using UnityEngine.XR.Hands.ProviderImplementation;

namespace Fingertrack.XRHands
{
    [System.Serializable] public class HandStateUnityEvent : UnityEvent<Handedness, ConnectionState, string> { }

    public class FingertrackXRHands : MonoBehaviour
    {
        [Tooltip("The service, e.g. http://127.0.0.1:8765")] public string serviceUrl = "http://127.0.0.1:8765";
        [Tooltip("A token with the viewer role")] public string token = "";
        [Tooltip("Session of the left hand (empty: no left hand)")] public string leftSession = "left";
        [Tooltip("Session of the right hand (empty: no right hand)")] public string rightSession = "right";
        [Tooltip("How far behind the newest frame hands are shown, s (interpolation delay)")] public float delaySeconds = 1.5f / 90f;

        /// <summary>hand, new state, the service's refusal reason (null unless Refused); main thread.</summary>
        public HandStateUnityEvent onConnectionStateChanged = new HandStateUnityEvent();

        public HandStream Left { get; private set; }
        public HandStream Right { get; private set; }
        public XRHandSubsystem Subsystem { get; private set; }

        XRHandProviderUtility.SubsystemUpdater updater;

        void OnEnable()
        {
            Left = Open(leftSession, Handedness.Left);
            Right = Open(rightSession, Handedness.Right);
            FingertrackHandFeed.Left = Left;
            FingertrackHandFeed.Right = Right;
            var descriptors = new List<XRHandSubsystemDescriptor>();
            SubsystemManager.GetSubsystemDescriptors(descriptors);
            foreach (var d in descriptors)
            {
                if (d.id != FingertrackHandProvider.Id) continue;
                Subsystem = d.Create();
                break;
            }
            if (Subsystem == null) { Debug.LogError("fingertrack: the XR Hands descriptor is not registered"); return; }
            updater = new XRHandProviderUtility.SubsystemUpdater(Subsystem);
            Subsystem.Start();
            updater.Start();
        }

        HandStream Open(string session, Handedness hand)
        {
            if (string.IsNullOrEmpty(session)) return null;
            var stream = new HandStream(serviceUrl, session, token);
            stream.Interpolator.DelayS = delaySeconds;
            stream.Client.OnProblem += text => Debug.LogWarning("fingertrack " + session + ": " + text);
            stream.StateChanged += s => onConnectionStateChanged.Invoke(hand, s, stream.Refused);
            stream.Start();
            return stream;
        }

        void Update()
        {
            // state changes and events also surface while XR Hands is not sampling (e.g. no XR device)
            if (Left != null) Left.Poll();
            if (Right != null) Right.Poll();
        }

        void OnDisable()
        {
            if (updater != null) updater.Destroy();
            updater = null;
            if (Subsystem != null) { Subsystem.Stop(); Subsystem.Destroy(); }
            Subsystem = null;
            FingertrackHandFeed.Left = FingertrackHandFeed.Right = null;
            if (Left != null) Left.Dispose();
            if (Right != null) Right.Dispose();
            Left = Right = null;
        }
    }
}
#endif
