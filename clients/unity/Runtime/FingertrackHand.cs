// Unity component: subscribes to one hand's stream and drives a rig of joint Transforms with the
// OpenXR joint poses (converted to Unity's frame) interpolated to the render time, and raises
// UnityEvents for gesture starts and ends with the pointing ray and for connection state changes
// (with the service's reason when it refuses). Compiled only inside Unity (UnityEngine is not
// available elsewhere); the logic it uses (HandStream, FrameInterpolator) is tested without Unity.
#if UNITY_5_3_OR_NEWER
using System;
using System.Collections.Generic;
using UnityEngine;
using UnityEngine.Events;

namespace Fingertrack
{
    [Serializable] public class GestureUnityEvent : UnityEvent<string, Vector3, Vector3> { }
    [Serializable] public class ConnectionUnityEvent : UnityEvent<ConnectionState, string> { }

    public class FingertrackHand : MonoBehaviour
    {
        [Tooltip("The service, e.g. http://127.0.0.1:8765")] public string serviceUrl = "http://127.0.0.1:8765";
        [Tooltip("The hand's session name (as the glove publishes it)")] public string session = "default";
        [Tooltip("A token with the viewer role")] public string token = "";
        [Tooltip("Joint Transforms by OpenXR joint name (palm, wrist, index_proximal, ...); unnamed joints are left alone")]
        public List<JointBinding> joints = new List<JointBinding>();
        [Tooltip("Frame whose space the service's stage space is: null = world")] public Transform stageOrigin;
        [Tooltip("Show the hand interpolated to the render time (off: the newest frame as it comes)")] public bool interpolate = true;
        [Tooltip("How far behind the newest frame the hand is shown when interpolating, s")] public float delaySeconds = 1.5f / 90f;

        /// <summary>gesture name, ray origin, ray direction (Unity space; zero when there is no ray)</summary>
        public GestureUnityEvent onGestureStart = new GestureUnityEvent();
        public GestureUnityEvent onGestureEnd = new GestureUnityEvent();
        /// <summary>new state and, when Refused, the service's reason (token, role, protocol)</summary>
        public ConnectionUnityEvent onConnectionStateChanged = new ConnectionUnityEvent();

        public Frame LastFrame { get { return stream != null ? stream.Newest : null; } }
        public string ActiveGesture { get { return LastFrame != null ? LastFrame.ActiveGesture : null; } }
        /// <summary>Connecting, Connected, Waiting (reconnecting), Refused or Stopped.</summary>
        public ConnectionState State { get { return stream != null ? stream.State : ConnectionState.Stopped; } }
        /// <summary>The service's reason for refusing, or null.</summary>
        public string Refused { get { return stream != null ? stream.Refused : null; } }
        /// <summary>The subscription (client counters, interpolator, clock offset), while enabled.</summary>
        public HandStream Stream { get { return stream; } }

        [Serializable] public class JointBinding { public string name; public Transform transform; }

        HandStream stream;
        readonly HandSample sample = new HandSample();
        readonly Transform[] byIndex = new Transform[Protocol.JointCount];

        void OnEnable()
        {
            Array.Clear(byIndex, 0, byIndex.Length);
            foreach (var b in joints)
            {
                var i = b.transform != null ? Array.IndexOf(Protocol.JointNames, b.name) : -1;
                if (i >= 0) byIndex[i] = b.transform;
                else if (b.transform != null) Debug.LogWarning("fingertrack: no OpenXR joint named '" + b.name + "'");
            }
            stream = new HandStream(serviceUrl, session, token);
            stream.Interpolator.DelayS = delaySeconds;
            stream.Client.OnProblem += text => Debug.LogWarning("fingertrack: " + text);
            stream.Gesture += OnGesture;
            stream.Error += e => Debug.LogWarning("fingertrack error " + e.Code + ": " + e.Detail);
            stream.StateChanged += s => onConnectionStateChanged.Invoke(s, stream.Refused);
            stream.Start();
        }

        void OnDisable()
        {
            if (stream != null) stream.Dispose();            // returns at once; the receive task ends by itself
            stream = null;
        }

        void OnGesture(GestureEvent g)
        {
            var o = g.Ray != null ? ToUnity(g.Ray.Origin) : Vector3.zero;
            var d = g.Ray != null ? ToUnityDirection(g.Ray.Direction) : Vector3.zero;
            (g.Event == "start" ? onGestureStart : onGestureEnd).Invoke(g.Gesture, o, d);
        }

        void Update()
        {
            if (stream == null) return;
            bool ok;
            if (interpolate) ok = stream.Sample(FingertrackClient.Now, sample);
            else
            {
                stream.Poll();
                var newest = stream.Newest;
                ok = newest != null && stream.Interpolator.SampleSource(newest.T, sample);
            }
            if (!ok) return;
            for (var i = 0; i < Protocol.JointCount; i++)
            {
                var tr = byIndex[i];
                if (tr == null || (sample.JointPresent & (1 << i)) == 0) continue;
                tr.SetPositionAndRotation(ToUnity(sample.Positions[i]), ToUnity(sample.Orientations[i]));
            }
        }

        Vector3 ToUnity(Vec3 v)
        {
            var u = v.ToUnity();
            var p = new Vector3((float)u.X, (float)u.Y, (float)u.Z);
            return stageOrigin != null ? stageOrigin.TransformPoint(p) : p;
        }

        Vector3 ToUnityDirection(Vec3 v)
        {
            var u = v.ToUnity();
            var d = new Vector3((float)u.X, (float)u.Y, (float)u.Z);
            return stageOrigin != null ? stageOrigin.TransformDirection(d) : d;
        }

        Quaternion ToUnity(Quat q)
        {
            var u = q.ToUnity();
            var r = new Quaternion((float)u.X, (float)u.Y, (float)u.Z, (float)u.W);
            return stageOrigin != null ? stageOrigin.rotation * r : r;
        }
    }
}
#endif
