// The compiled parts of the optimizer and its validation (opt2skill.trajopt.native), one Python module.
// Pinocchio first: it sets Boost.MPL's list sizes for its joint variant before anything includes MPL.
#include "feedback_replay.hpp"
#include "barrier_cost.hpp"
#include "matched_euler.hpp"
#include "frame_tracking.hpp"

BOOST_PYTHON_MODULE(_native) {
  boost::python::import("crocoddyl");  // registers the base classes these derive from
  matched_euler::expose();
  barrier_cost::expose();
  feedback_replay::expose();
  frame_tracking::expose();
}
