// The validation's feedback replay (opt2skill.data.replay.Replayer.feedback_states) as one C++ loop.
//
// At every 1-kHz physics step: u = tau_ref - K_k (x (-) x_ref) + the joints' losses, sent through the
// servos' targets, then MuJoCo's mj_step. The Python loop spent about as long around mj_step as in
// it (14,000 steps per 14-s walk). The law, the order of its terms and the fall check every 50 steps
// are the Python loop's; the arrays are the ones it builds (`Replayer.feedback_references`), passed
// by address after the Python side has checked their shapes, types and contiguity.
#pragma once

// clang-format off
#include <pinocchio/algorithm/joint-configuration.hpp>  // before Boost.Python (module.cpp)
// clang-format on
#include <mujoco/mujoco.h>

#include <algorithm>
#include <boost/python.hpp>
#include <cmath>
#include <cstdint>
#include <stdexcept>

namespace feedback_replay {

namespace bp = boost::python;
using Vec = Eigen::VectorXd;
using ConstMap = Eigen::Map<const Eigen::VectorXd>;
using GainMap = Eigen::Map<const Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>;

template <typename T>
T* at(const bp::dict& pointers, const char* key) {
  return reinterpret_cast<T*>(static_cast<std::uintptr_t>(bp::extract<unsigned long long>(pointers[key])));
}

// The rotation between the reference's and the robot's base orientation (MuJoCo quaternions, w first).
inline double angle_between(const double* q_ref, const double* q) {
  const double w = q_ref[0] * q[0] + q_ref[1] * q[1] + q_ref[2] * q[2] + q_ref[3] * q[3];
  const double x = q_ref[0] * q[1] - q_ref[1] * q[0] - q_ref[2] * q[3] + q_ref[3] * q[2];
  const double y = q_ref[0] * q[2] + q_ref[1] * q[3] - q_ref[2] * q[0] - q_ref[3] * q[1];
  const double z = q_ref[0] * q[3] - q_ref[1] * q[2] + q_ref[2] * q[1] - q_ref[3] * q[0];
  return 2.0 * std::atan2(std::sqrt(x * x + y * y + z * z), std::fabs(w));
}

// Runs up to `nstep` steps from MjData's current state; returns the steps taken (fewer after a fall).
// `pointers`: qpos_ref, q_ref, v_ref, tau_ref, node (int64), gains, target_ref, kd_v_ref (with `pd`),
// kp, kd, damping, frictionloss; outputs qpos (nstep x nq), sensors (nstep x nsensordata) and, when
// given, props (nstep x the rest of MuJoCo's qpos).
inline int run(std::uintptr_t model_address, std::uintptr_t data_address, const pinocchio::Model& pin_model,
               const bp::dict& pointers, int nstep, bool pd, bool joint_losses, double smoothing, double fall_height,
               double fall_angle) {
  const mjModel* m = reinterpret_cast<const mjModel*>(model_address);
  mjData* d = reinterpret_cast<mjData*>(data_address);
  const int nq = pin_model.nq, nv = pin_model.nv, nu = nv - 6;
  if (nq > m->nq || nv > m->nv || nu != m->nu) throw std::invalid_argument("the MuJoCo and Pinocchio models differ");
  const double* qpos_ref = at<const double>(pointers, "qpos_ref");
  const double* q_ref = at<const double>(pointers, "q_ref");
  const double* v_ref = at<const double>(pointers, "v_ref");
  const double* tau_ref = at<const double>(pointers, "tau_ref");
  const std::int64_t* node = at<const std::int64_t>(pointers, "node");
  const double* gains = at<const double>(pointers, "gains");
  const double* target_ref = at<const double>(pointers, "target_ref");
  const double* kd_v_ref = pd ? at<const double>(pointers, "kd_v_ref") : nullptr;
  const ConstMap kp(at<const double>(pointers, "kp"), nu), kd(at<const double>(pointers, "kd"), nu);
  const ConstMap damping(at<const double>(pointers, "damping"), nu);
  const ConstMap frictionloss(at<const double>(pointers, "frictionloss"), nu);
  double* out_qpos = at<double>(pointers, "qpos");
  double* out_sensors = at<double>(pointers, "sensors");
  double* out_props = pointers.has_key("props") ? at<double>(pointers, "props") : nullptr;
  const int nprop = m->nq - nq;

  Vec q(nq), dx(2 * nv), u(nu), losses = Vec::Zero(nu);
  for (int i = 0; i < nstep; ++i) {
    const double* qpos = d->qpos;
    const double* qvel = d->qvel;
    // MuJoCo (w, x, y, z) to Pinocchio (x, y, z, w) for the base's quaternion.
    q.head<3>() = Eigen::Map<const Eigen::Vector3d>(qpos);
    q.segment<3>(3) = Eigen::Map<const Eigen::Vector3d>(qpos + 4);
    q[6] = qpos[3];
    q.tail(nq - 7) = Eigen::Map<const Vec>(qpos + 7, nq - 7);
    dx.head(nv) = pinocchio::difference(pin_model, ConstMap(q_ref + i * nq, nq), q);
    // Pinocchio's base velocity is the world-frame one rotated into the base frame.
    const double w = qpos[3], x = qpos[4], y = qpos[5], z = qpos[6], a = qvel[0], b = qvel[1], c = qvel[2];
    const double* vr = v_ref + i * nv;
    dx[nv] = (1 - 2 * (y * y + z * z)) * a + (2 * (x * y + w * z)) * b + (2 * (x * z - w * y)) * c - vr[0];
    dx[nv + 1] = (2 * (x * y - w * z)) * a + (1 - 2 * (x * x + z * z)) * b + (2 * (y * z + w * x)) * c - vr[1];
    dx[nv + 2] = (2 * (x * z + w * y)) * a + (2 * (y * z - w * x)) * b + (1 - 2 * (x * x + y * y)) * c - vr[2];
    for (int j = 3; j < nv; ++j) dx[nv + j] = qvel[j] - vr[j];
    const ConstMap joint_velocity(qvel + 6, nu);
    if (joint_losses) {
      for (int j = 0; j < nu; ++j)
        losses[j] = damping[j] * joint_velocity[j] + frictionloss[j] * std::tanh(joint_velocity[j] / smoothing);
    }
    u = ConstMap(tau_ref + i * nu, nu) - GainMap(gains + node[i] * nu * 2 * nv, nu, 2 * nv) * dx + losses;
    for (int j = 0; j < nu; ++j) {
      d->ctrl[j] = pd ? target_ref[i * nu + j] + (u[j] + kd_v_ref[i * nu + j]) / kp[j]
                      : qpos[7 + j] + (u[j] + kd[j] * joint_velocity[j]) / kp[j];
    }
    mj_step(m, d);
    std::copy(d->qpos, d->qpos + nq, out_qpos + i * nq);
    if (out_props) std::copy(d->qpos + nq, d->qpos + m->nq, out_props + i * nprop);
    std::copy(d->sensordata, d->sensordata + m->nsensordata, out_sensors + i * m->nsensordata);
    if (i % 50 == 0) {
      const double* ref = qpos_ref + std::min(i + 1, nstep - 1) * nq;
      if (ref[2] - d->qpos[2] > fall_height || angle_between(ref + 3, d->qpos + 3) > fall_angle) return i + 1;
    }
  }
  return nstep;
}

inline void expose() {
  bp::def("feedback_replay", &run,
          bp::args("model_address", "data_address", "pin_model", "pointers", "nstep", "pd", "joint_losses", "smoothing",
                   "fall_height", "fall_angle"),
          "The validation's feedback replay in C++ (opt2skill.data.replay); returns the steps taken.");
}

}  // namespace feedback_replay
