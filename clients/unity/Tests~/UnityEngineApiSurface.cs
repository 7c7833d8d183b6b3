// API SURFACE FOR COMPILATION ONLY, NOT AN IMPLEMENTATION OF UNITY.
//
// The UnityEngine types and members the package's code uses (signatures as in Unity 2021.3's
// scripting API), so that the runtime, the XR Hands provider and, with UNITY_5_3_OR_NEWER, the
// MonoBehaviours compile under Mono. Bodies do only what the harness needs (poses are plain data)
// or nothing. Nothing here ships in the package: Tests~ is hidden from Unity.
using System;
using System.Collections.Generic;

namespace UnityEngine
{
    public struct Vector3
    {
        public float x, y, z;
        public Vector3(float x, float y, float z) { this.x = x; this.y = y; this.z = z; }
        public static Vector3 zero { get { return new Vector3(0f, 0f, 0f); } }
    }

    public struct Quaternion
    {
        public float x, y, z, w;
        public Quaternion(float x, float y, float z, float w) { this.x = x; this.y = y; this.z = z; this.w = w; }
        public static Quaternion identity { get { return new Quaternion(0f, 0f, 0f, 1f); } }
        public static Quaternion operator *(Quaternion lhs, Quaternion rhs) { throw new NotSupportedException("API surface"); }
    }

    public struct Pose
    {
        public Vector3 position;
        public Quaternion rotation;
        public Pose(Vector3 position, Quaternion rotation) { this.position = position; this.rotation = rotation; }
        public static Pose identity { get { return new Pose(new Vector3(), Quaternion.identity); } }
    }

    public enum RuntimeInitializeLoadType
    {
        AfterSceneLoad = 0,
        BeforeSceneLoad = 1,
        AfterAssembliesLoaded = 2,
        BeforeSplashScreen = 3,
        SubsystemRegistration = 4,
    }

    [AttributeUsage(AttributeTargets.Method, AllowMultiple = false)]
    public class RuntimeInitializeOnLoadMethodAttribute : Attribute
    {
        public RuntimeInitializeOnLoadMethodAttribute(RuntimeInitializeLoadType loadType) { this.loadType = loadType; }
        public RuntimeInitializeLoadType loadType { get; private set; }
    }

    [AttributeUsage(AttributeTargets.Field, Inherited = true, AllowMultiple = false)]
    public class TooltipAttribute : Attribute
    {
        public readonly string tooltip;
        public TooltipAttribute(string tooltip) { this.tooltip = tooltip; }
    }

    public class Object { }
    public class Component : Object { public Transform transform { get { return null; } } }
    public class Behaviour : Component { public bool enabled { get; set; } }
    public class MonoBehaviour : Behaviour { }

    public class Transform : Component
    {
        public Quaternion rotation { get; set; }
        public void SetPositionAndRotation(Vector3 position, Quaternion rotation) { }
        public Vector3 TransformPoint(Vector3 position) { return position; }
        public Vector3 TransformDirection(Vector3 direction) { return direction; }
    }

    public static class Debug
    {
        public static void LogWarning(object message) { }
        public static void LogError(object message) { }
    }

    public static class SubsystemManager
    {
        public static void GetSubsystemDescriptors<T>(List<T> descriptors) where T : ISubsystemDescriptor { }
    }

    public interface ISubsystemDescriptor { string id { get; } }
    public interface ISubsystem { void Start(); void Stop(); void Destroy(); bool running { get; } }
}

namespace UnityEngine.Events
{
    public abstract class UnityEventBase { }

    public class UnityEvent<T0, T1> : UnityEventBase
    {
        public void Invoke(T0 arg0, T1 arg1) { }
    }

    public class UnityEvent<T0, T1, T2> : UnityEventBase
    {
        public void Invoke(T0 arg0, T1 arg1, T2 arg2) { }
    }
}
