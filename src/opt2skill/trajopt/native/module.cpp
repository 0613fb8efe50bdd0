// The compiled parts of the optimizer and its validation (opt2skill.trajopt.native), one Python module.
// Pinocchio first: it sets Boost.MPL's list sizes for its joint variant before anything includes MPL.
#include "feedback_replay.hpp"
#include "barrier_cost.hpp"
#include "matched_euler.hpp"
#include "frame_tracking.hpp"

// Whether this CPU runs the module built for AVX2 and FMA (`simd_module.cpp`).
inline bool cpu_has_avx2_fma() {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
#else
  return false;
#endif
}

BOOST_PYTHON_MODULE(_native) {
  boost::python::import("crocoddyl");  // registers the base classes these derive from
  matched_euler::expose();
  barrier_cost::expose();
  feedback_replay::expose();
  frame_tracking::expose();
  boost::python::def("cpu_has_avx2_fma", cpu_has_avx2_fma, "Whether this CPU has AVX2 and FMA.");
}
