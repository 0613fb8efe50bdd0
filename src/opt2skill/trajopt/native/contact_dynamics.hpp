// Crocoddyl's contact forward dynamics whose derivatives' matrix products are compiled in this module
// (opt2skill.trajopt.native, `simd_module.cpp`: AVX2 and FMA, which the wheel is built without).
//
// A node's `calcDiff` spends about a fifth of its time multiplying the KKT inverse's blocks into the
// dynamics' and the forces' Jacobians (nv = 26, up to 12 contact rows for Digit); Pinocchio's
// derivatives, the contacts', the actuation's and the costs' own derivatives stay the wheels' calls; their
// sum is this module's (`cost_sum.hpp`).
// The steps are those of Crocoddyl 3.2.1's `calcDiff` (contact-fwddyn.hxx), in its order of
// operations, so that compiled for baseline x86-64 they give its derivatives to the bit. `calc` is
// Crocoddyl's, its first step (`computeAllTerms`) replaced by the terms it reads (`dynamics_terms.hpp`):
// the same dynamics, forces and costs to round-off, the node's calc about a fifth faster for Digit
// (14.1 -> 11.4 us with one foot, 16.7 -> 14.5 us with two). Models without constraints
// only (the optimizer's; the constructor has no manager).
#pragma once

#include <boost/python.hpp>
#include <crocoddyl/multibody/actions/contact-fwddyn.hpp>
#include <pinocchio/algorithm/contact-dynamics.hpp>
#include <pinocchio/algorithm/rnea-derivatives.hpp>

#include "cost_sum.hpp"
#include "dynamics_terms.hpp"

#include <memory>
#include <stdexcept>
#include <string>

namespace contact_dynamics {

namespace bp = boost::python;
using crocoddyl::ActuationModelAbstract;
using crocoddyl::ContactModelMultiple;
using crocoddyl::CostModelSum;
using crocoddyl::DifferentialActionDataAbstract;
using crocoddyl::DifferentialActionDataContactFwdDynamics;
using crocoddyl::DifferentialActionModelContactFwdDynamics;
using crocoddyl::StateMultibody;
using Vector = Eigen::Ref<const Eigen::VectorXd>;

class ContactFwdDynamics : public DifferentialActionModelContactFwdDynamics {
 public:
  ContactFwdDynamics(std::shared_ptr<StateMultibody> state, std::shared_ptr<ActuationModelAbstract> actuation,
                     std::shared_ptr<ContactModelMultiple> contacts, std::shared_ptr<CostModelSum> costs,
                     double damping, bool enable_force)
      : DifferentialActionModelContactFwdDynamics(state, actuation, contacts, costs, damping, enable_force),
        with_force_derivatives_(enable_force) {}  // the base keeps its flag private, without a getter

  // Crocoddyl 3.2.1's calc (contact-fwddyn.hxx) step by step, `computeAllTerms` excepted.
  void calc(const std::shared_ptr<DifferentialActionDataAbstract>& data, const Vector& x, const Vector& u) override {
    check_sizes("calc", x, u);
    auto* d = static_cast<DifferentialActionDataContactFwdDynamics*>(data.get());
    const std::size_t nc = get_contacts()->get_nc();
    const Eigen::Ref<const Eigen::VectorXd> q = x.head(state_->get_nq());
    const Eigen::Ref<const Eigen::VectorXd> v = x.tail(state_->get_nv());
    dynamics_terms::compute(get_pinocchio(), d->pinocchio, q, v);
    pinocchio::computeCentroidalMomentum(get_pinocchio(), d->pinocchio);
    // Crocoddyl adds its own armature only once set (`set_armature`); until then it is zero.
    d->pinocchio.M.diagonal() += get_armature();
    get_actuation()->calc(d->multibody.actuation, x, u);
    get_contacts()->calc(d->multibody.contacts, x);
    pinocchio::forwardDynamics(get_pinocchio(), d->pinocchio, d->multibody.actuation->tau,
                               d->multibody.contacts->Jc.topRows(nc), d->multibody.contacts->a0.head(nc),
                               get_damping_factor());
    d->xout = d->pinocchio.ddq;
    get_contacts()->updateAcceleration(d->multibody.contacts, d->pinocchio.ddq);
    get_contacts()->updateForce(d->multibody.contacts, d->pinocchio.lambda_c);
    d->multibody.joint->a = d->pinocchio.ddq;
    d->multibody.joint->tau = u;
    get_costs()->calc(d->costs, x, u);
    d->cost = d->costs->cost;
  }

  void calc(const std::shared_ptr<DifferentialActionDataAbstract>& data, const Vector& x) override {
    DifferentialActionModelContactFwdDynamics::calc(data, x);  // the terminal node: Crocoddyl's own
  }

  void calcDiff(const std::shared_ptr<DifferentialActionDataAbstract>& data, const Vector& x,
                const Vector& u) override {
    check_sizes("calcDiff", x, u);
    ContactModelMultiple& contacts = *get_contacts();
    const std::size_t nv = state_->get_nv(), nc = contacts.get_nc();
    auto* d = static_cast<DifferentialActionDataContactFwdDynamics*>(data.get());
    const auto q = x.head(state_->get_nq());
    const auto v = x.tail(nv);
    auto& forces = d->multibody.contacts;

    // The dynamics' derivatives in the wheels: Pinocchio's RNEA derivatives under the contact forces,
    // the contacts' own terms, the KKT matrix's inverse, the actuation's and contacts' Jacobians.
    d->Kinv.resize(nv + nc, nv + nc);  // Eigen cannot take the block of a block here (Crocoddyl's note)
    pinocchio::computeRNEADerivatives(get_pinocchio(), d->pinocchio, q, v, d->xout, forces->fext);
    contacts.updateRneaDiff(forces, d->pinocchio);
    pinocchio::getKKTContactDynamicMatrixInverse(get_pinocchio(), d->pinocchio, forces->Jc.topRows(nc), d->Kinv);
    get_actuation()->calcDiff(d->multibody.actuation, x, u);
    contacts.calcDiff(forces, x);

    // The products: the acceleration's Jacobians, then the forces'.
    const auto accel_by_torque = d->Kinv.topLeftCorner(nv, nv);
    const auto accel_by_drift = d->Kinv.topRightCorner(nv, nc);
    const auto force_by_torque = d->Kinv.bottomLeftCorner(nc, nv);
    const auto force_by_drift = d->Kinv.bottomRightCorner(nc, nc);
    const auto& tau = d->multibody.actuation;
    d->Fx.leftCols(nv).noalias() = -accel_by_torque * d->pinocchio.dtau_dq;
    d->Fx.rightCols(nv).noalias() = -accel_by_torque * d->pinocchio.dtau_dv;
    d->Fx.noalias() -= accel_by_drift * forces->da0_dx.topRows(nc);
    d->Fx.noalias() += accel_by_torque * tau->dtau_dx;
    d->Fu.noalias() = accel_by_torque * tau->dtau_du;
    d->multibody.joint->da_dx = d->Fx;
    d->multibody.joint->da_du = d->Fu;
    if (with_force_derivatives_) {
      d->df_dx.topLeftCorner(nc, nv).noalias() = force_by_torque * d->pinocchio.dtau_dq;
      d->df_dx.topRightCorner(nc, nv).noalias() = force_by_torque * d->pinocchio.dtau_dv;
      d->df_dx.topRows(nc).noalias() += force_by_drift * forces->da0_dx.topRows(nc);
      d->df_dx.topRows(nc).noalias() -= force_by_torque * tau->dtau_dx;
      d->df_du.topRows(nc).noalias() = -force_by_torque * tau->dtau_du;
      contacts.updateAccelerationDiff(forces, d->Fx.bottomRows(nv));
      contacts.updateForceDiff(forces, d->df_dx.topRows(nc), d->df_du.topRows(nc));
    }
    cost_sum::calcDiff(*get_costs(), *d->costs, x, u);  // Crocoddyl's sum over the blocks costs fill
  }

  void calcDiff(const std::shared_ptr<DifferentialActionDataAbstract>& data, const Vector& x) override {
    DifferentialActionModelContactFwdDynamics::calcDiff(data, x);  // the terminal node: costs only
  }

 private:
  void check_sizes(const char* what, const Vector& x, const Vector& u) const {
    if (static_cast<std::size_t>(x.size()) != state_->get_nx() || static_cast<std::size_t>(u.size()) != nu_) {
      throw std::invalid_argument(std::string("ContactFwdDynamics.") + what + ": x has size " +
                                  std::to_string(x.size()) + " (nx " + std::to_string(state_->get_nx()) + "), u " +
                                  std::to_string(u.size()) + " (nu " + std::to_string(nu_) + ")");
    }
  }

  bool with_force_derivatives_;
};

inline void expose() {
  bp::class_<ContactFwdDynamics, bp::bases<DifferentialActionModelContactFwdDynamics>,
             std::shared_ptr<ContactFwdDynamics>, boost::noncopyable>(
      "ContactFwdDynamics",
      "Crocoddyl's contact forward dynamics, its derivatives' matrix products compiled for AVX2 and FMA (C++).",
      bp::init<std::shared_ptr<StateMultibody>, std::shared_ptr<ActuationModelAbstract>,
               std::shared_ptr<ContactModelMultiple>, std::shared_ptr<CostModelSum>, double, bool>(
          bp::args("self", "state", "actuation", "contacts", "costs", "damping", "enable_force")));
}

}  // namespace contact_dynamics
