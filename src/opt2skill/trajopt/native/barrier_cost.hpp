// A residual cost whose derivatives are skipped where its activation is flat, and formed over its
// active rows alone where few are active (C++).
//
// Crocoddyl's CostModelResidual::calcDiff always differentiates the residual and multiplies
// Lxx = Rx^T diag(Arr) Rx (and Lxu, Luu) over every row (crocoddyl/core/costs/residual.hxx and
// residual-base.hxx, 3.2.1). For a quadratic barrier inside its bounds (a contact wrench inside its
// cone, joints inside their limits), which is most nodes in most iterations, Ar and Arr are zero and
// all of that work gives zeros: about 13 us of a single-support node's 71-us calcDiff, 26 of a
// double-support node's 90 (docs/trajopt.md). Here the activation's derivatives come first; where
// Ar and Arr are all zero the cost's derivatives are set to zero without touching the residual.
// Where a few rows are active (a cone's edge, a limit reached: a quarter of a walk's barriers at its
// solution, one or two rows of 17 or 52), the residual is differentiated and the products run over
// those rows alone, one outer product each, in Crocoddyl's row order; with half the rows or more
// active, and for the residuals with products of their own (Crocoddyl's state and control residuals:
// per joint, already cheap), Crocoddyl's products run. Inactive rows add exact zeros to Crocoddyl's
// sums, so the results are Crocoddyl's to round-off (tests/test_trajopt_native.py).
#pragma once

#include <boost/python.hpp>
#include <crocoddyl/core/costs/residual.hpp>
#include <crocoddyl/core/residuals/control.hpp>
#include <crocoddyl/multibody/residuals/state.hpp>

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

// Whether row i of the activation has a slope or a curvature.
inline bool active(const ActivationDataAbstract& activation, Eigen::Index i) {
  return activation.Ar[i] != 0.0 || activation.Arr.diagonal()[i] != 0.0;
}

inline Eigen::Index active_rows(const ActivationDataAbstract& activation) {
  Eigen::Index n = 0;
  for (Eigen::Index i = 0; i < activation.Ar.size(); ++i) n += active(activation, i);
  return n;
}

// Crocoddyl's Gauss-Newton products (ResidualModelAbstract::calcCostDiff, 3.2.1: the same blocks by the
// residual's q/v/u dependence) summed over the active rows only, an outer product per row, in order.
inline void cost_diff_over_active_rows(const ResidualModelAbstract& residual, CostDataAbstract& data,
                                       bool update_u) {
  const auto& rd = *data.residual;
  const auto& ad = *data.activation;
  const auto curvature = ad.Arr.diagonal();
  const Eigen::Index nv = static_cast<Eigen::Index>(residual.get_state()->get_nv());
  const bool q = residual.get_q_dependent(), v = residual.get_v_dependent();
  const bool with_u = residual.get_u_dependent() && residual.get_nu() != 0 && update_u;
  const Eigen::Index first = q ? 0 : nv, count = (q ? nv : 0) + (v ? nv : 0);
  if (with_u) {
    data.Lu.setZero();
    data.Luu.setZero();
    if (count) data.Lxu.middleRows(first, count).setZero();
  }
  if (count) {
    data.Lx.segment(first, count).setZero();
    data.Lxx.block(first, first, count, count).setZero();
  }
  for (Eigen::Index i = 0; i < ad.Ar.size(); ++i) {
    if (!active(ad, i)) continue;
    if (with_u) {
      const auto ru = rd.Ru.row(i);
      data.Lu.noalias() += ru.transpose() * ad.Ar[i];
      data.Luu.noalias() += ru.transpose() * (curvature[i] * ru);
    }
    if (count) {
      const auto rx = rd.Rx.row(i).segment(first, count);
      data.Lx.segment(first, count).noalias() += rx.transpose() * ad.Ar[i];
      data.Lxx.block(first, first, count, count).noalias() += rx.transpose() * (curvature[i] * rx);
      if (with_u) data.Lxu.middleRows(first, count).noalias() += rx.transpose() * (curvature[i] * rd.Ru.row(i));
    }
  }
}

class BarrierCost : public CostModelResidual {
 public:
  BarrierCost(std::shared_ptr<StateAbstract> state, std::shared_ptr<ActivationModelAbstract> activation,
              std::shared_ptr<ResidualModelAbstract> residual)
      : CostModelResidual(checked(state, activation, residual), activation, residual),
        rowwise_(!std::dynamic_pointer_cast<crocoddyl::ResidualModelState>(residual) &&
                 !std::dynamic_pointer_cast<crocoddyl::ResidualModelControl>(residual)) {}

  void calcDiff(const std::shared_ptr<CostDataAbstract>& data, const Eigen::Ref<const Eigen::VectorXd>& x,
                const Eigen::Ref<const Eigen::VectorXd>& u) override {
    activation_->calcDiff(data->activation, data->residual->r);  // r is calc's, as in Crocoddyl's order
    const Eigen::Index rows = active_rows(*data->activation);
    if (rows == 0) {
      data->Lx.setZero();
      data->Lu.setZero();
      data->Lxx.setZero();
      data->Lxu.setZero();
      data->Luu.setZero();
      return;
    }
    residual_->calcDiff(data->residual, x, u);
    differentiate(data, rows, true);
  }

  void calcDiff(const std::shared_ptr<CostDataAbstract>& data, const Eigen::Ref<const Eigen::VectorXd>& x) override {
    if (!residual_->get_q_dependent() && !residual_->get_v_dependent()) {
      data->Lx.setZero();
      data->Lxx.setZero();
      return;
    }
    activation_->calcDiff(data->activation, data->residual->r);
    const Eigen::Index rows = active_rows(*data->activation);
    if (rows == 0) {
      data->Lx.setZero();
      data->Lxx.setZero();
      return;
    }
    residual_->calcDiff(data->residual, x);
    differentiate(data, rows, false);
  }

 private:
  void differentiate(const std::shared_ptr<CostDataAbstract>& data, Eigen::Index rows, bool update_u) {
    if (rowwise_ && 2 * rows < static_cast<Eigen::Index>(residual_->get_nr())) {
      cost_diff_over_active_rows(*residual_, *data, update_u);
    } else {
      residual_->calcCostDiff(data, data->residual, data->activation, update_u);
    }
  }

  bool rowwise_;  // whether the residual's cost products are the base class's (dense), so rows may be skipped
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
