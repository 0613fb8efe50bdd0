// A residual cost whose derivatives are skipped where its activation is flat (C++).
//
// Crocoddyl's CostModelResidual::calcDiff always differentiates the residual and multiplies
// Lxx = Rx^T diag(Arr) Rx (and Lxu, Luu) over every row (crocoddyl/core/costs/residual.hxx and
// residual-base.hxx, 3.2.1). For a quadratic barrier inside its bounds (a contact wrench inside its
// cone, joints inside their limits), which is most nodes in most iterations, Ar and Arr are zero and
// all of that work gives zeros: about 13 us of a single-support node's 71-us calcDiff, 26 of a
// double-support node's 90 (docs/trajopt.md). Here the activation's derivatives come first; where
// Ar and Arr are all zero the cost's derivatives are set to zero without touching the residual,
// and otherwise Crocoddyl's own code runs as before. So the results equal Crocoddyl's, exactly.
#pragma once

#include <boost/python.hpp>
#include <crocoddyl/core/costs/residual.hpp>

#include <memory>
#include <stdexcept>

namespace barrier_cost {

namespace bp = boost::python;
using crocoddyl::ActivationDataAbstract;
using crocoddyl::ActivationModelAbstract;
using crocoddyl::CostDataAbstract;
using crocoddyl::CostModelResidual;
using crocoddyl::ResidualModelAbstract;
using crocoddyl::StateAbstract;

// Checked before the base class's constructor, which dereferences them.
inline std::shared_ptr<StateAbstract> checked(std::shared_ptr<StateAbstract> state,
                                              const std::shared_ptr<ActivationModelAbstract>& activation,
                                              const std::shared_ptr<ResidualModelAbstract>& residual) {
  if (!state || !activation || !residual) {
    throw std::invalid_argument("BarrierCostModel needs a state, an activation and a residual, got None");
  }
  return state;
}

inline bool flat(const ActivationDataAbstract& activation) {
  return activation.Ar.isZero(0.0) && activation.Arr.diagonal().isZero(0.0);
}

class BarrierCost : public CostModelResidual {
 public:
  BarrierCost(std::shared_ptr<StateAbstract> state, std::shared_ptr<ActivationModelAbstract> activation,
              std::shared_ptr<ResidualModelAbstract> residual)
      : CostModelResidual(checked(state, activation, residual), activation, residual) {}

  void calcDiff(const std::shared_ptr<CostDataAbstract>& data, const Eigen::Ref<const Eigen::VectorXd>& x,
                const Eigen::Ref<const Eigen::VectorXd>& u) override {
    activation_->calcDiff(data->activation, data->residual->r);  // r is calc's, as in Crocoddyl's order
    if (flat(*data->activation)) {
      data->Lx.setZero();
      data->Lu.setZero();
      data->Lxx.setZero();
      data->Lxu.setZero();
      data->Luu.setZero();
      return;
    }
    residual_->calcDiff(data->residual, x, u);
    residual_->calcCostDiff(data, data->residual, data->activation);
  }

  void calcDiff(const std::shared_ptr<CostDataAbstract>& data, const Eigen::Ref<const Eigen::VectorXd>& x) override {
    if (!residual_->get_q_dependent() && !residual_->get_v_dependent()) {
      data->Lx.setZero();
      data->Lxx.setZero();
      return;
    }
    activation_->calcDiff(data->activation, data->residual->r);
    if (flat(*data->activation)) {
      data->Lx.setZero();
      data->Lxx.setZero();
      return;
    }
    residual_->calcDiff(data->residual, x);
    residual_->calcCostDiff(data, data->residual, data->activation, false);
  }
};

// Called from the module's init (module.cpp), after crocoddyl's base classes are registered.
inline void expose() {
  bp::class_<BarrierCost, bp::bases<CostModelResidual>, std::shared_ptr<BarrierCost>, boost::noncopyable>(
      "BarrierCostModel",
      "Crocoddyl's residual cost, its derivatives skipped where the activation is flat (C++).",
      bp::init<std::shared_ptr<StateAbstract>, std::shared_ptr<ActivationModelAbstract>,
               std::shared_ptr<ResidualModelAbstract>>(bp::args("self", "state", "activation", "residual")));
}

}  // namespace barrier_cost
