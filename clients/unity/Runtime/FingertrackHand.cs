// Unity component: subscribes to one hand's stream and drives a rig of joint Transforms with the
// OpenXR joint poses (converted to Unity's frame), and raises UnityEvents for gesture starts and
// ends with the pointing ray. Compiled only inside Unity (UnityEngine is not available elsewhere).
#if UNITY_5_3_OR_NEWER
using System;
using System.Collections.Generic;
using UnityEngine;
using UnityEngine.Events;

namespace Fingertrack
{
    [Serializable] public class GestureUnityEvent : UnityEvent<string, Vector3, Vector3> { }

    public class FingertrackHand : MonoBehaviour
    {
        [Tooltip("The service, e.g. http://127.0.0.1:8765")] public string serviceUrl = "http://127.0.0.1:8765";
        [Tooltip("The hand's session name (as the glove publishes it)")] public string session = "right";
        [Tooltip("A token with the viewer role")] public string token = "";
        [Tooltip("Joint Transforms by OpenXR joint name (palm, wrist, index_proximal, ...); unnamed joints are left alone")]
        public List<JointBinding> joints = new List<JointBinding>();
        [Tooltip("Frame whose space the service's stage space is: null = world")] public Transform stageOrigin;

        /// <summary>gesture name, ray origin, ray direction (Unity space; zero when there is no ray)</summary>
        public GestureUnityEvent onGestureStart = new GestureUnityEvent();
        public GestureUnityEvent onGestureEnd = new GestureUnityEvent();

        public Frame LastFrame { get; private set; }
        public string ActiveGesture { get { return LastFrame != null ? LastFrame.ActiveGesture : null; } }

        [Serializable] public class JointBinding { public string name; public Transform transform; }

        FingertrackClient client;
        readonly Dictionary<string, Transform> byName = new Dictionary<string, Transform>();

        void OnEnable()
        {
            byName.Clear();
            foreach (var b in joints) if (b.transform != null && !string.IsNullOrEmpty(b.name)) byName[b.name] = b.transform;
            client = new FingertrackClient(serviceUrl, session, token);
            client.OnProblem += text => Debug.LogWarning("fingertrack: " + text);
            client.Start();
        }

        void OnDisable()
        {
            if (client != null) client.Dispose();
            client = null;
        }

        void Update()
        {
            if (client == null) return;
            Frame newest = null;
            ServiceMessage m;
            while (client.TryDequeue(out m))
            {
                var f = m as Frame;
                if (f != null) { newest = f; continue; }
                var g = m as GestureEvent;
                if (g != null)
                {
                    var o = g.Ray != null ? ToUnity(g.Ray.Origin) : Vector3.zero;
                    var d = g.Ray != null ? ToUnityDirection(g.Ray.Direction) : Vector3.zero;
                    (g.Event == "start" ? onGestureStart : onGestureEnd).Invoke(g.Gesture, o, d);
                    continue;
                }
                var e = m as ErrorMessage;
                if (e != null) Debug.LogWarning("fingertrack error " + e.Code + ": " + e.Detail);
            }
            if (newest == null) return;
            LastFrame = newest;                               // only the newest frame of this Update is applied
            foreach (var kv in newest.Joints)
            {
                Transform tr;
                if (!byName.TryGetValue(kv.Key, out tr)) continue;
                tr.SetPositionAndRotation(ToUnity(kv.Value.Position), ToUnity(kv.Value.Orientation));
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
