// Box-FDDP whose backward pass forms its quadratic models in this module (opt2skill.trajopt.native,
// `simd_module.cpp`), compiled for AVX2 and FMA.
//
// Crocoddyl's wheel is built for baseline x86-64 (SSE2: no AVX or FMA instruction in libcrocoddyl.so),
// and the backward pass is mostly dense products of the node's derivatives with the next node's value
// function (ndx = 52 for Digit): a quarter of a walk's solve (docs/trajopt.md). The two steps below
// are the published Box-FDDP recursion (Mastalli et al., ICRA 2020) in the order of operations
// Crocoddyl 3.2.1 uses, so that compiled for baseline x86-64 they give its backward pass to the bit
// (checked when this was written); the box-QP gains, the line search and everything else stay
// Crocoddyl's own. Compiled with FMA they differ from Crocoddyl's at round-off.
#pragma once

#include <boost/python.hpp>
#include <crocoddyl/core/solvers/box-fddp.hpp>

#include <cmath>
#include <memory>

namespace riccati {

namespace bp = boost::python;
using crocoddyl::ActionDataAbstract;
using crocoddyl::ActionModelAbstract;
using crocoddyl::ShootingProblem;

class BoxFDDP : public crocoddyl::SolverBoxFDDP {
 public:
  explicit BoxFDDP(std::shared_ptr<ShootingProblem> problem) : crocoddyl::SolverBoxFDDP(std::move(problem)) {}

  // Q at node t: the node's cost derivatives plus the next node's value function through the dynamics.
  void computeActionValueFunction(const std::size_t t, const std::shared_ptr<ActionModelAbstract>& model,
                                  const std::shared_ptr<ActionDataAbstract>& data) override {
    const Eigen::MatrixXd& next_hessian = Vxx_[t + 1];
    const Eigen::VectorXd& next_gradient = Vx_[t + 1];
    FxTVxx_p_.noalias() = data->Fx.transpose() * next_hessian;
    Qx_[t] = data->Lx;
    Qx_[t].noalias() += data->Fx.transpose() * next_gradient;
    Qxx_[t] = data->Lxx;
    Qxx_[t].noalias() += FxTVxx_p_ * data->Fx;
    if (model->get_nu() == 0) return;  // an impulse node
    FuTVxx_p_[t].noalias() = data->Fu.transpose() * next_hessian;
    Qu_[t] = data->Lu;
    Qu_[t].noalias() += data->Fu.transpose() * next_gradient;
    Quu_[t] = data->Luu;
    Quu_[t].noalias() += FuTVxx_p_[t] * data->Fu;
    Qxu_[t] = data->Lxu;
    Qxu_[t].noalias() += FxTVxx_p_ * data->Fu;
    if (!std::isnan(preg_)) Quu_[t].diagonal().array() += preg_;
  }

  // V at node t under the gains just computed (symmetrized, regularized, and moved to the end of the
  // node's gap while the trajectory has gaps).
  void computeValueFunction(const std::size_t t, const std::shared_ptr<ActionModelAbstract>& model) override {
    Vx_[t] = Qx_[t];
    Vxx_[t] = Qxx_[t];
    if (model->get_nu() != 0) {
      Quuk_[t].noalias() = Quu_[t] * k_[t];
      Vx_[t].noalias() -= K_[t].transpose() * Qu_[t];
      Vxx_[t].noalias() -= Qxu_[t] * K_[t];
    }
    Vxx_tmp_ = 0.5 * (Vxx_[t] + Vxx_[t].transpose());
    Vxx_[t] = Vxx_tmp_;
    if (!std::isnan(preg_)) Vxx_[t].diagonal().array() += preg_;
    if (!is_feasible_) Vx_[t].noalias() += Vxx_[t] * fs_[t];
  }
};

inline void expose() {
  bp::class_<BoxFDDP, bp::bases<crocoddyl::SolverBoxFDDP>, boost::noncopyable>(
      "BoxFDDP",
      "Crocoddyl's Box-FDDP with the backward pass's products compiled for AVX2 and FMA (C++).",
      bp::init<std::shared_ptr<ShootingProblem>>(bp::args("self", "problem")));
}

}  // namespace riccati
