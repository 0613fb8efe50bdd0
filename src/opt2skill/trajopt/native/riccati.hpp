// Box-FDDP whose backward pass forms its quadratic models in this module (opt2skill.trajopt.native,
// `simd_module.cpp`), compiled for AVX2 and FMA.
//
// Crocoddyl's wheel is built for baseline x86-64 (SSE2: no AVX or FMA instruction in libcrocoddyl.so),
// and the backward pass is mostly dense products of the node's derivatives with the next node's value
// function (ndx = 52 for Digit): a quarter of a walk's solve (docs/trajopt.md). The two steps below
// are the published Box-FDDP recursion (Mastalli et al., ICRA 2020) in the order of operations
// Crocoddyl 3.2.1 uses, so that compiled for baseline x86-64 they give its backward pass to the bit
// (checked when this was written); the box-QP gains, the acceptance of a step and everything else stay
// Crocoddyl's own. Compiled with FMA they differ from Crocoddyl's at round-off. The forward pass is
// Crocoddyl's too, except that a trial on a trajectory without gaps stops once its cost can no longer
// be accepted (below): the same iterations, about a fifth of the line search's node evaluations fewer.
#pragma once

#include <boost/python.hpp>
#include <crocoddyl/core/solvers/box-fddp.hpp>

#include <algorithm>
#include <cmath>
#include <memory>
#include <stdexcept>

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

  // A line-search trial that stops once it cannot be accepted. On a trajectory without gaps, Box-FDDP
  // accepts a step length a when the cost falls by more than th_acceptstep * dVexp(a), with dVexp(a) =
  // a (dg + a dq / 2) known before the trial (FDDP's expectedImprovement adds nothing without gaps),
  // unless |dg| < th_grad. Every node's cost is >= 0 (the optimizer's are weighted squares and
  // barriers, times dt; a node cost below zero, once seen, turns the stop off), so the
  // cost summed so far never exceeds the trial's total: once cost - sum <= th_acceptstep * dVexp, the
  // trial is rejected whatever the remaining nodes give, and they are not evaluated. A rejected trial
  // leaves nothing the solver reads (a later trial rolls out from x0 again; the derivatives are the
  // last calcDiff's), so the iterations are Crocoddyl's. The test keeps a margin of 1e-9 of the cost on
  // the side of going on, against the different rounding of dVexp here (FMA). Trajectories with gaps:
  // Crocoddyl's own pass (their expected improvement needs the whole trial).
  void forwardPass(const double steplength) override {
    if (!is_feasible_ || steplength > 1.0 || steplength < 0.0) {
      crocoddyl::SolverBoxFDDP::forwardPass(steplength);
      return;
    }
    const double expected = steplength * (dg_ + 0.5 * steplength * dq_);
    const bool can_stop = std::abs(dg_) >= th_grad_;
    // Stop when cost - sum <= bound. With dVexp < 0 Crocoddyl accepts nothing here; max(dVexp, 0) keeps
    // the test right where the two roundings of dVexp straddle zero.
    const double bound = th_acceptstep_ * std::max(expected, 0.0) - 1e-9 * std::max(1.0, std::abs(cost_));
    const auto& models = problem_->get_runningModels();
    const auto& datas = problem_->get_runningDatas();
    const std::size_t T = problem_->get_T();
    cost_try_ = 0.0;
    xnext_ = problem_->get_x0();
    ++trials_;
    for (std::size_t t = 0; t < T; ++t) {
      const std::shared_ptr<ActionModelAbstract>& m = models[t];
      const std::shared_ptr<ActionDataAbstract>& d = datas[t];
      xs_try_[t] = xnext_;
      m->get_state()->diff(xs_[t], xs_try_[t], dx_[t]);
      if (m->get_nu() != 0) {
        us_try_[t].noalias() = us_[t] - k_[t] * steplength - K_[t] * dx_[t];
        if (m->get_has_control_limits()) us_try_[t] = us_try_[t].cwiseMax(m->get_u_lb()).cwiseMin(m->get_u_ub());
        m->calc(d, xs_try_[t], us_try_[t]);
      } else {
        m->calc(d, xs_try_[t]);
      }
      xnext_ = d->xnext;
      cost_try_ += d->cost;
      ++nodes_;
      if (d->cost < 0.0) negative_cost_seen_ = true;  // the bound needs costs >= 0: never stop again
      if (!std::isfinite(cost_try_) || !std::isfinite(xnext_.lpNorm<Eigen::Infinity>())) {
        throw std::runtime_error("forward_error");  // as Crocoddyl's pass: the trial is skipped
      }
      if (can_stop && !negative_cost_seen_ && cost_ - cost_try_ <= bound) {
        nodes_skipped_ += T - t;  // the terminal node counts as one
        ++stopped_;
        return;
      }
    }
    xs_try_.back() = xnext_;
    problem_->get_terminalModel()->calc(problem_->get_terminalData(), xs_try_.back());
    cost_try_ += problem_->get_terminalData()->cost;
    ++nodes_;
    if (!std::isfinite(cost_try_)) throw std::runtime_error("forward_error");
  }

  // Line-search counts since construction (trials on trajectories without gaps): what the stop saves.
  std::size_t trials() const { return trials_; }
  std::size_t stopped() const { return stopped_; }
  std::size_t nodes() const { return nodes_; }
  std::size_t nodes_skipped() const { return nodes_skipped_; }

 private:
  std::size_t trials_ = 0, stopped_ = 0, nodes_ = 0, nodes_skipped_ = 0;
  bool negative_cost_seen_ = false;
};

inline void expose() {
  bp::class_<BoxFDDP, bp::bases<crocoddyl::SolverBoxFDDP>, boost::noncopyable>(
      "BoxFDDP",
      "Crocoddyl's Box-FDDP with the backward pass's products compiled for AVX2 and FMA (C++).",
      bp::init<std::shared_ptr<ShootingProblem>>(bp::args("self", "problem")))
      .add_property("line_search_trials", &BoxFDDP::trials, "line-search trials on trajectories without gaps")
      .add_property("line_search_stopped", &BoxFDDP::stopped, "those stopped once they could not be accepted")
      .add_property("line_search_nodes", &BoxFDDP::nodes, "nodes those trials evaluated")
      .add_property("line_search_nodes_skipped", &BoxFDDP::nodes_skipped, "nodes the stopped trials left out");
}

}  // namespace riccati
