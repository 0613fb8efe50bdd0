// Crocoddyl's cost sum's derivatives (CostModelSum::calcDiff, cost-sum.hxx 3.2.1) with its weighted sums
// compiled in this module (AVX2 and FMA, `simd_module.cpp`) and restricted to the blocks a cost can fill.
//
// Crocoddyl adds every cost's five derivative blocks in full, 4216 numbers for Digit (ndx 52, nu 20),
// although a frame's pose or the centre of mass depends on q alone (a quarter of Lxx, no u blocks), a
// torque term on u alone, and a barrier inside its bounds gives zeros everywhere: about 9 costs per node,
// added after every node's derivatives. Here each cost's own calcDiff runs as before, in the same order,
// and only the blocks its residual depends on (its q/v/u flags, which Crocoddyl's Gauss-Newton products
// follow) are added; a quadratic barrier whose activation is flat adds nothing. The blocks left out are
// zeros, so the sums are Crocoddyl's to round-off (FMA).
#pragma once

#include <crocoddyl/core/activations/quadratic-barrier.hpp>
#include <crocoddyl/core/costs/cost-sum.hpp>

#include <memory>
#include <stdexcept>
#include <string>

namespace cost_sum {

using crocoddyl::CostDataAbstract;
using crocoddyl::CostDataSum;
using crocoddyl::CostItem;
using crocoddyl::CostModelSum;
using Vector = Eigen::Ref<const Eigen::VectorXd>;

// A quadratic barrier whose residual is strictly inside its bounds: no slope, no curvature, and so (by the
// Gauss-Newton products of a residual cost) no derivative at all.
inline bool flat_barrier(const CostItem& item, const CostDataAbstract& data) {
  if (!std::dynamic_pointer_cast<crocoddyl::ActivationModelQuadraticBarrier>(item.cost->get_activation())) {
    return false;
  }
  return data.activation->Ar.isZero(0.0) && data.activation->Arr.diagonal().isZero(0.0);
}

inline void calcDiff(const CostModelSum& model, CostDataSum& data, const Vector& x, const Vector& u) {
  if (data.costs.size() != model.get_costs().size()) {
    throw std::invalid_argument("cost_sum::calcDiff: " + std::to_string(data.costs.size()) + " cost datas for " +
                                std::to_string(model.get_costs().size()) + " costs");
  }
  const Eigen::Index nv = static_cast<Eigen::Index>(model.get_state()->get_nv());
  const Eigen::Index nu = static_cast<Eigen::Index>(model.get_nu());
  data.Lx.setZero();
  data.Lu.setZero();
  data.Lxx.setZero();
  data.Lxu.setZero();
  data.Luu.setZero();
  auto it_d = data.costs.begin();
  for (auto it_m = model.get_costs().begin(); it_m != model.get_costs().end(); ++it_m, ++it_d) {
    const CostItem& item = *it_m->second;
    if (!item.active) continue;
    const std::shared_ptr<CostDataAbstract>& cost_data = it_d->second;
    item.cost->calcDiff(cost_data, x, u);
    if (flat_barrier(item, *cost_data)) continue;
    const auto& residual = *item.cost->get_residual();
    const bool q = residual.get_q_dependent(), v = residual.get_v_dependent();
    const bool with_u = residual.get_u_dependent() && nu != 0;
    const Eigen::Index first = q ? 0 : nv, count = (q ? nv : 0) + (v ? nv : 0);
    const double w = item.weight;
    const CostDataAbstract& d = *cost_data;
    if (count) {
      data.Lx.segment(first, count) += w * d.Lx.segment(first, count);
      data.Lxx.block(first, first, count, count) += w * d.Lxx.block(first, first, count, count);
    }
    if (with_u) {
      data.Lu += w * d.Lu;
      data.Luu += w * d.Luu;
      if (count) data.Lxu.middleRows(first, count) += w * d.Lxu.middleRows(first, count);
    }
  }
}

}  // namespace cost_sum
