// The optimizer's parts compiled for AVX2 and FMA (opt2skill.trajopt.native: `load_simd`), one Python
// module apart from `_native`: it is built with other instruction sets, and loaded only where the CPU
// has them. Its Eigen code is compiled with 16-byte alignment, the layout of the wheels' objects it reads.
#include "contact_dynamics.hpp"
#include "riccati.hpp"

BOOST_PYTHON_MODULE(_native_simd) {
  boost::python::import("crocoddyl");  // registers the base classes these derive from
  riccati::expose();
  contact_dynamics::expose();
}
