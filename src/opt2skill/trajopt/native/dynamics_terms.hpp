// The terms of Pinocchio's `computeAllTerms` that the optimizer's contact dynamics and costs read,
// and none of the others (opt2skill.trajopt.native, the AVX2 module: `contact_dynamics.hpp`'s calc).
//
// Crocoddyl's contact dynamics starts every `calc` with `computeAllTerms`, which besides the mass
// matrix, the bias forces and the kinematics also forms the Jacobians' time variations, the centroidal
// map's time variation, the subtrees' centres of mass and velocities and the mechanical energy. None of
// those is read by the forward dynamics, the contacts, the optimizer's residuals (frames, centre of
// mass, wrench cones, state, control, joint acceleration) or the derivatives, which form their own in
// `computeRNEADerivatives`. Leaving them out takes a node's calc from 14.1 to 11.4 us for Digit.
//
// One forward pass (Featherstone's recursion: placements, velocities, bias accelerations with and
// without gravity, the joint Jacobians in the world frame, each body's inertia in the world frame and
// its bias force) and one backward pass (the composite inertias, the mass matrix's upper triangle as
// J^T Ag over each subtree, the bias forces' projections) fill:
//   oMi, liMi, v, ov, a, a_gf, J, oYcrb, h, f, M (upper triangle, plus the model's armature), nle, Ag,
//   Jcom (Ag's linear rows over the total mass), and Ag's angular rows about the centre of mass.
// Left as they were: dJ, doYcrb, dAg, dhg, Ig, g, vcom, com/mass of the subtrees, the energies.
// `computeCentroidalMomentum`, which the caller runs next as Crocoddyl does, sets com[0], mass, h, hg.
#pragma once

#include <pinocchio/algorithm/centroidal.hpp>
#include <pinocchio/multibody/data.hpp>
#include <pinocchio/multibody/model.hpp>
#include <pinocchio/multibody/visitor.hpp>
#include <pinocchio/spatial/act-on-set.hpp>

namespace dynamics_terms {

using Model = pinocchio::Model;
using Data = pinocchio::Data;
using Config = Eigen::Ref<const Eigen::VectorXd>;

struct ForwardStep : public pinocchio::fusion::JointUnaryVisitorBase<ForwardStep> {
  typedef boost::fusion::vector<const Model&, Data&, const Config&, const Config&> ArgsType;

  template <typename JointModel>
  static void algo(const pinocchio::JointModelBase<JointModel>& joint,
                   pinocchio::JointDataBase<typename JointModel::JointDataDerived>& joint_data, const Model& model,
                   Data& data, const Config& q, const Config& v) {
    const pinocchio::JointIndex i = joint.id();
    const pinocchio::JointIndex parent = model.parents[i];
    joint.calc(joint_data.derived(), q, v);

    data.liMi[i] = model.jointPlacements[i] * joint_data.M();
    data.v[i] = joint_data.v();
    if (parent > 0) {
      data.oMi[i] = data.oMi[parent] * data.liMi[i];
      data.v[i] += data.liMi[i].actInv(data.v[parent]);
    } else {
      data.oMi[i] = data.liMi[i];
    }
    data.ov[i] = data.oMi[i].act(data.v[i]);
    data.oYcrb[i] = data.oMi[i].act(model.inertias[i]);
    joint.jointCols(data.J) = data.oMi[i].act(joint_data.S());

    // The acceleration with zero joint accelerations: the contacts' drift reads `a`, the bias forces
    // take gravity in `a_gf`.
    data.a_gf[i] = data.a[i] = joint_data.c() + (data.v[i] ^ joint_data.v());
    if (parent > 0) data.a[i] += data.liMi[i].actInv(data.a[parent]);
    data.a_gf[i] += data.liMi[i].actInv(data.a_gf[parent]);

    data.h[i] = model.inertias[i] * data.v[i];
    data.f[i] = model.inertias[i] * data.a_gf[i] + data.v[i].cross(data.h[i]);
  }
};

struct BackwardStep : public pinocchio::fusion::JointUnaryVisitorBase<BackwardStep> {
  typedef boost::fusion::vector<const Model&, Data&> ArgsType;

  template <typename JointModel>
  static void algo(const pinocchio::JointModelBase<JointModel>& joint,
                   pinocchio::JointDataBase<typename JointModel::JointDataDerived>& joint_data, const Model& model,
                   Data& data) {
    const pinocchio::JointIndex i = joint.id();
    const pinocchio::JointIndex parent = model.parents[i];
    const auto joint_cols = joint.jointCols(data.J);
    auto momentum_cols = joint.jointCols(data.Ag);

    // oYcrb[i] is the subtree's composite inertia here: its children added theirs before.
    pinocchio::motionSet::inertiaAction(data.oYcrb[i], joint_cols, momentum_cols);
    data.M.block(joint.idx_v(), joint.idx_v(), joint.nv(), data.nvSubtree[i]).noalias() =
        joint_cols.transpose() * data.Ag.middleCols(joint.idx_v(), data.nvSubtree[i]);
    joint.jointVelocitySelector(data.nle).noalias() = joint_data.S().transpose() * data.f[i];

    data.oYcrb[parent] += data.oYcrb[i];
    data.f[parent] += data.liMi[i].act(data.f[i]);
  }
};

// Fills the terms listed above for configuration q and velocity v (sizes checked by the caller).
inline void compute(const Model& model, Data& data, const Config& q, const Config& v) {
  data.v[0].setZero();
  data.a[0].setZero();
  data.a_gf[0] = -model.gravity;
  data.oYcrb[0].setZero();
  for (pinocchio::JointIndex i = 1; i < static_cast<pinocchio::JointIndex>(model.njoints); ++i) {
    ForwardStep::run(model.joints[i], data.joints[i], ForwardStep::ArgsType(model, data, q, v));
  }
  data.f[0].setZero();
  for (pinocchio::JointIndex i = static_cast<pinocchio::JointIndex>(model.njoints) - 1; i > 0; --i) {
    BackwardStep::run(model.joints[i], data.joints[i], BackwardStep::ArgsType(model, data));
  }
  data.M.diagonal() += model.armature;

  const double mass = data.oYcrb[0].mass();
  const Eigen::Vector3d com = data.oYcrb[0].lever();
  auto linear = data.Ag.topRows<3>();
  auto angular = data.Ag.bottomRows<3>();
  for (Eigen::Index k = 0; k < model.nv; ++k) angular.col(k) += linear.col(k).cross(com);
  data.Jcom = linear / mass;
}

}  // namespace dynamics_terms
