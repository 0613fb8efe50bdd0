// The matched integrator (opt2skill.trajopt.integrator) as a Crocoddyl C++ action model.
//
// Crocoddyl's semi-implicit Euler moves the configuration by v dt + a * time_step2_ and uses
// time_step2_ for that term in calc and in calcDiff alike (crocoddyl/core/integrator/euler.hxx,
// 3.2.1). With time_step2_ = dt^2 (N + 1) / (2 N) instead of dt^2 it is the position update of N
// Euler substeps with the acceleration held, which is all the matched integrator changes. Everything
// else (velocity update, cost scaling, derivatives, data, control bounds) is Crocoddyl's own.
#pragma once

#include <boost/python.hpp>
#include <crocoddyl/core/integrator/euler.hpp>

#include <memory>
#include <stdexcept>
#include <string>

namespace matched_euler {

namespace bp = boost::python;
using crocoddyl::DifferentialActionModelAbstract;
using crocoddyl::IntegratedActionModelEuler;

// Checked before the base class's constructor, which dereferences the model.
inline std::shared_ptr<DifferentialActionModelAbstract> checked(std::shared_ptr<DifferentialActionModelAbstract> model,
                                                                double dt, int substeps) {
  if (!model) throw std::invalid_argument("MatchedEulerModel needs a differential action model, got None");
  if (!(dt > 0.0) || substeps < 1) {
    throw std::invalid_argument("MatchedEulerModel needs dt > 0 and substeps >= 1, got " + std::to_string(dt) +
                                ", " + std::to_string(substeps));
  }
  return model;
}

class MatchedEuler : public IntegratedActionModelEuler {
 public:
  MatchedEuler(std::shared_ptr<DifferentialActionModelAbstract> model, double dt, int substeps)
      : IntegratedActionModelEuler(checked(model, dt, substeps), dt, false), substeps_(substeps) {
    time_step2_ = dt * dt * (substeps + 1) / (2.0 * substeps);
  }
  int substeps() const { return substeps_; }
  double position_dt2() const { return time_step2_; }

 private:
  int substeps_;
};

// Called from the module's init (module.cpp), after crocoddyl's base classes are registered.
inline void expose() {
  bp::class_<MatchedEuler, bp::bases<IntegratedActionModelEuler>, std::shared_ptr<MatchedEuler>, boost::noncopyable>(
      "MatchedEulerModel",
      "Semi-implicit Euler over dt with the position update of `substeps` Euler substeps (C++).",
      bp::init<std::shared_ptr<DifferentialActionModelAbstract>, double, int>(
          bp::args("self", "differential", "dt", "substeps")))
      // Read-only: Crocoddyl's setter would reset the position factor to dt^2 without a word.
      .add_property("dt", &MatchedEuler::get_dt, "the node's time step (read-only)")
      .add_property("substeps", &MatchedEuler::substeps, "Euler substeps per node whose position update this matches")
      .add_property("position_dt2", &MatchedEuler::position_dt2, "the position update's factor of the acceleration");
}

}  // namespace matched_euler
