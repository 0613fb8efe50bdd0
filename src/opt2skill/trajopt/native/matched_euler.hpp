// The matched integrator (opt2skill.trajopt.integrator) as a Crocoddyl C++ action model.
//
// Crocoddyl's semi-implicit Euler moves the configuration by v dt + a * time_step2_ and uses
// time_step2_ for that term in calc and in calcDiff alike (crocoddyl/core/integrator/euler.hxx,
// 3.2.1). With time_step2_ = dt^2 (N + 1) / (2 N) instead of dt^2 it is the position update of N
// Euler substeps with the acceleration held, which is all the matched integrator changes. Everything
// else (velocity update, cost scaling, derivatives, data, control bounds) is Crocoddyl's own.
//
// Nodes of the same structure may share one differential data (`share_differential_data`): a
// node's data then keeps only what the solver reads (xnext, cost, the derivatives), and the
// contact dynamics and costs run in a scratch that stays in the core's cache. Looping over a
// window's nodes, each with its own differential data, made calcDiff twice as slow as the same
// node repeated (docs/trajopt.md); with the scratch, calcDiff first repeats the node's calc, since
// the scratch holds whichever node was evaluated last.
#pragma once

#include <boost/python.hpp>
#include <crocoddyl/core/integrator/euler.hpp>

#include <memory>
#include <stdexcept>
#include <string>

namespace matched_euler {

namespace bp = boost::python;
using crocoddyl::ActionDataAbstract;
using crocoddyl::DifferentialActionDataAbstract;
using crocoddyl::DifferentialActionModelAbstract;
using crocoddyl::IntegratedActionDataEuler;
using crocoddyl::IntegratedActionModelEuler;
using Vector = Eigen::Ref<const Eigen::VectorXd>;

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

  // Datas made from now on evaluate the differential model in `scratch`, which must be a data of a
  // differential model of the same structure (state, actuation, contacts and costs by name and kind):
  // the caller's promise, checked by type here and by equal results in tests/test_trajopt_native.py.
  void share_differential_data(const std::shared_ptr<DifferentialActionDataAbstract>& scratch) {
    if (!scratch || !differential_->checkData(scratch)) {
      throw std::invalid_argument("share_differential_data needs a data of this node's kind of differential model");
    }
    scratch_ = scratch;
  }
  bool shares_data() const { return static_cast<bool>(scratch_); }

  // With a scratch, the data is made through `WithScratch`, so that Crocoddyl's data constructor takes the
  // scratch as its differential data instead of making a full one (a Pinocchio data and the contacts' and
  // costs' datas) that would be dropped at once: a third of a walk's build (0.139 -> 0.094 CPU s).
  std::shared_ptr<ActionDataAbstract> createData() override {
    if (!scratch_) return IntegratedActionModelEuler::createData();
    WithScratch<double> view(*this, scratch_);
    return std::allocate_shared<IntegratedActionDataEuler>(Eigen::aligned_allocator<IntegratedActionDataEuler>(),
                                                           &view);
  }

  void calcDiff(const std::shared_ptr<ActionDataAbstract>& data, const Vector& x, const Vector& u) override {
    if (shared(data)) IntegratedActionModelEuler::calc(data, x, u);
    IntegratedActionModelEuler::calcDiff(data, x, u);
  }

  void calcDiff(const std::shared_ptr<ActionDataAbstract>& data, const Vector& x) override {
    if (shared(data)) IntegratedActionModelEuler::calc(data, x);
    IntegratedActionModelEuler::calcDiff(data, x);
  }

 private:
  // What Crocoddyl's data constructors read of a model (IntegratedActionDataEulerTpl and its bases,
  // 3.2.1), this model's own figures, except that its differential model "creates" the scratch.
  template <typename Scalar>
  class WithScratch {
   public:
    struct Differential {
      std::shared_ptr<DifferentialActionDataAbstract> scratch;
      std::shared_ptr<DifferentialActionDataAbstract> createData() const { return scratch; }
    };
    WithScratch(const MatchedEuler& model, std::shared_ptr<DifferentialActionDataAbstract> scratch)
        : model_(model), differential_{std::move(scratch)} {}
    const Differential* get_differential() const { return &differential_; }
    const auto& get_control() const { return model_.get_control(); }
    const auto& get_state() const { return model_.get_state(); }
    std::size_t get_nu() const { return model_.get_nu(); }
    std::size_t get_nr() const { return model_.get_nr(); }
    std::size_t get_ng() const { return model_.get_ng(); }
    std::size_t get_nh() const { return model_.get_nh(); }
    std::size_t get_ng_T() const { return model_.get_ng_T(); }
    std::size_t get_nh_T() const { return model_.get_nh_T(); }

   private:
    const MatchedEuler& model_;
    Differential differential_;
  };

  bool shared(const std::shared_ptr<ActionDataAbstract>& data) const {
    return scratch_ && static_cast<IntegratedActionDataEuler*>(data.get())->differential == scratch_;
  }

  int substeps_;
  std::shared_ptr<DifferentialActionDataAbstract> scratch_;
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
      .add_property("position_dt2", &MatchedEuler::position_dt2, "the position update's factor of the acceleration")
      .def("share_differential_data", &MatchedEuler::share_differential_data, bp::args("self", "scratch"),
           "Datas made from now on evaluate the differential model in `scratch`, a data of a differential "
           "model of the same structure; calcDiff then repeats the node's calc first.")
      .add_property("shares_data", &MatchedEuler::shares_data, "whether new datas use a shared differential data");
}

}  // namespace matched_euler
