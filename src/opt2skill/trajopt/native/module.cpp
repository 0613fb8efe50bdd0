// The compiled parts of the optimizer (opt2skill.trajopt.native), one Python module.
#include "barrier_cost.hpp"
#include "matched_euler.hpp"

BOOST_PYTHON_MODULE(_native) {
  boost::python::import("crocoddyl");  // registers the base classes these derive from
  matched_euler::expose();
  barrier_cost::expose();
}
