// The 200 Hz frames' tracking law (opt2skill.trajopt.tracking) over one coarse node, as one C++ loop.
//
// Each frame: the reference steps on with the plan's acceleration held (after the node's first
// frame), the desired acceleration a_des = a_plan + Kp (x_ref (-) x)_q + Kd (x_ref (-) x)_v, the
// torque u = clip(u_k + G (a_des - a(u_k))) with a(u_k) from the node's 5-ms model at (x, u_k), then
// the frame's own step at (x, u); its state, torque and world-axis contact wrenches are written and
// x moves to the step's end. The law and the order of its terms are the Python policy's
// (`tracking.track`); the Python loop (`frames.complete`) spent about three times the two model
// evaluations around them. A frame whose wrenches leave their cones is left to the caller, which
// projects its torque (an NNLS, `frames.ContactCones.project`): the loop returns at it with the
// model's data evaluated at (x, u) and u written out.
//
// The law's gain G = (Fu^T M Fu + 1e-9 tr(.) I)^-1 Fu^T M (`tracking._least_squares_gain`) is computed
// here too, at the node's first frame (x, u_k): Fu = da/du is Crocoddyl's (its calcDiff's product of the
// KKT matrix's inverse and the actuation's Jacobian) without the rest of the node's derivatives, which
// the law does not read; the Python policy spent three times the loop's share on those and the gain.
#pragma once

#include <boost/python.hpp>
#include <crocoddyl/core/integrator/euler.hpp>
#include <crocoddyl/multibody/actions/contact-fwddyn.hpp>
#include <pinocchio/algorithm/contact-dynamics.hpp>

#include <cstdint>
#include <stdexcept>
#include <string>
#include <vector>

namespace frame_tracking {

namespace bp = boost::python;
using Vec = Eigen::VectorXd;
using Map = Eigen::Map<Eigen::VectorXd>;
using ConstMap = Eigen::Map<const Eigen::VectorXd>;
using RowMajor = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
using ConstMatrixMap = Eigen::Map<const RowMajor>;
using ContactDynamicsData = crocoddyl::DifferentialActionDataContactFwdDynamicsTpl<double>;

template <typename T>
T* at(const bp::dict& pointers, const char* key) {
  return reinterpret_cast<T*>(static_cast<std::uintptr_t>(bp::extract<unsigned long long>(pointers[key])));
}

// One active contact of the node: its name in the contact data, its row in the frame's wrench array,
// whether it is a 6D (flat) contact whose wrench is rotated out of its frame, and that frame.
struct Contact {
  std::string name;
  int row;
  bool flat;
  std::size_t frame;
};

// The law's gain at (x, u_k) into `gain` (nu x nv, row-major), leaving the data evaluated there.
inline void least_squares_gain(const std::shared_ptr<crocoddyl::ActionModelAbstract>& fine,
                               const std::shared_ptr<crocoddyl::ActionDataAbstract>& fine_data,
                               ContactDynamicsData& dynamics, const Eigen::Ref<const Vec>& x,
                               const Eigen::Ref<const Vec>& u_k, double* gain) {
  auto euler = std::dynamic_pointer_cast<crocoddyl::IntegratedActionModelEuler>(fine);
  auto model = euler ? std::dynamic_pointer_cast<crocoddyl::DifferentialActionModelContactFwdDynamics>(
                           euler->get_differential())
                     : nullptr;
  if (!model) throw std::invalid_argument("track_frames needs contact forward dynamics inside the Euler model");
  fine->calc(fine_data, x, u_k);  // the mass matrix, its factorization and the contacts' Jacobian at x
  const Eigen::Index nv = model->get_state()->get_nv(), nu = model->get_nu();
  const Eigen::Index nc = model->get_contacts()->get_nc();
  Eigen::MatrixXd kkt_inverse(nv + nc, nv + nc);
  pinocchio::getKKTContactDynamicMatrixInverse(model->get_pinocchio(), dynamics.pinocchio,
                                               dynamics.multibody.contacts->Jc.topRows(nc), kkt_inverse);
  model->get_actuation()->calcDiff(dynamics.multibody.actuation, x, u_k);
  const Eigen::MatrixXd fu = kkt_inverse.topLeftCorner(nv, nv) * dynamics.multibody.actuation->dtau_du;
  Eigen::MatrixXd mass = dynamics.pinocchio.M;  // Pinocchio fills the upper triangle
  mass.triangularView<Eigen::StrictlyLower>() = mass.transpose();
  const Eigen::MatrixXd weighted = fu.transpose() * mass;
  Eigen::MatrixXd hessian = weighted * fu;
  hessian.diagonal().array() += 1e-9 * hessian.trace();
  Eigen::Map<RowMajor>(gain, nu, nv) = hessian.partialPivLu().solve(weighted);
}

// Frames `first` to `count - 1` of a node; returns the index of the first frame not written: `count`,
// or a frame whose wrenches left their cones (with `cone_rows` > 0), or the frame after one whose
// next state is not finite (x then holds it). `pointers` (row-major float64, checked by the caller):
// x (nx, in/out: the frame's state), x_ref (nx, in/out: its reference), u_k (nu), a_plan (nv), gain
// (nu x nv, out when `first` is 0: the law's gain, computed at the node's first state), limit (nu), u (nu, out: the last frame's torque), q (count x nq), v (count x nv), tau
// (count x nu), wrench (count x ncontact_rows x 6), and with `cone_rows` > 0 cone (cone_rows x
// cone_cols), lower and upper (cone_rows, tolerances included).
inline int run(const std::shared_ptr<crocoddyl::ActionModelAbstract>& fine,
               const std::shared_ptr<crocoddyl::ActionDataAbstract>& fine_data,
               const std::shared_ptr<crocoddyl::StateAbstract>& state, const bp::dict& pointers, int first, int count,
               double kp, double kd, double frame_dt, const bp::list& contact_list, int wrench_rows, int cone_rows,
               int cone_cols) {
  auto* integrated = dynamic_cast<crocoddyl::IntegratedActionDataEuler*>(fine_data.get());
  if (!fine || !integrated) throw std::invalid_argument("track_frames needs an Euler action model and its data");
  auto* dynamics = dynamic_cast<ContactDynamicsData*>(integrated->differential.get());
  if (!dynamics) throw std::invalid_argument("track_frames needs contact forward dynamics inside the Euler model");
  const int nq = state->get_nq(), nv = state->get_nv(), nx = state->get_nx(), ndx = state->get_ndx();
  const int nu = fine->get_nu();
  if (count < 0 || first < 0 || first > count) throw std::invalid_argument("track_frames: bad frame range");
  std::vector<Contact> contacts;
  for (bp::ssize_t i = 0; i < bp::len(contact_list); ++i) {
    const bp::tuple c = bp::extract<bp::tuple>(contact_list[i]);
    contacts.push_back({bp::extract<std::string>(c[0]), bp::extract<int>(c[1]), bp::extract<bool>(c[2]),
                        bp::extract<std::size_t>(c[3])});
  }
  auto& stack = dynamics->multibody.contacts->contacts;
  std::vector<const crocoddyl::ContactDataAbstract*> force_of;
  for (const Contact& c : contacts) {
    auto it = stack.find(c.name);
    if (it == stack.end() || c.row < 0 || c.row >= wrench_rows) {
      throw std::invalid_argument("track_frames: no contact '" + c.name + "' in the node's data, or its row is out of range");
    }
    force_of.push_back(it->second.get());
  }
  int force_size = 0;
  for (const Contact& c : contacts) force_size += c.flat ? 6 : 3;
  if (cone_rows > 0 && force_size != cone_cols) {
    throw std::invalid_argument("track_frames: the cone's columns are not the contacts' forces");
  }
  Map x(at<double>(pointers, "x"), nx), x_ref(at<double>(pointers, "x_ref"), nx), u(at<double>(pointers, "u"), nu);
  const ConstMap u_k(at<const double>(pointers, "u_k"), nu), a_plan(at<const double>(pointers, "a_plan"), nv);
  const ConstMap limit(at<const double>(pointers, "limit"), nu);
  if (first == 0) least_squares_gain(fine, fine_data, *dynamics, x, u_k, at<double>(pointers, "gain"));
  const ConstMatrixMap gain(at<const double>(pointers, "gain"), nu, nv);
  double* out_q = at<double>(pointers, "q");
  double* out_v = at<double>(pointers, "v");
  double* out_tau = at<double>(pointers, "tau");
  double* out_wrench = at<double>(pointers, "wrench");
  const double* cone = cone_rows > 0 ? at<const double>(pointers, "cone") : nullptr;
  const double* lower = cone_rows > 0 ? at<const double>(pointers, "lower") : nullptr;
  const double* upper = cone_rows > 0 ? at<const double>(pointers, "upper") : nullptr;

  Vec step = Vec::Zero(ndx), error(ndx), a_des(nv), forces(cone_cols > 0 ? cone_cols : 0), x_ref_before(nx);
  step.tail(nv) = a_plan * frame_dt;  // the reference's velocity change, the same every frame
  for (int i = first; i < count; ++i) {
    if (i > 0) {
      step.head(nv) = x_ref.tail(nv) * frame_dt + a_plan * (frame_dt * frame_dt);
      x_ref_before = x_ref;  // integrate's input and output must not alias
      state->integrate(x_ref_before, step, x_ref);
    }
    state->diff(x, x_ref, error);
    a_des = a_plan + kp * error.head(nv) + kd * error.tail(nv);
    fine->calc(fine_data, x, u_k);
    u = u_k + gain * (a_des - dynamics->xout);
    u = u.cwiseMax(-limit).cwiseMin(limit);
    fine->calc(fine_data, x, u);
    if (cone_rows > 0) {
      int col = 0;
      for (std::size_t j = 0; j < contacts.size(); ++j) {
        const int size = contacts[j].flat ? 6 : 3;
        forces.segment(col, size) = force_of[j]->f.toVector().head(size);
        col += size;
      }
      const Vec rows = ConstMatrixMap(cone, cone_rows, cone_cols) * forces;
      for (int r = 0; r < cone_rows; ++r) {
        if (!(rows[r] <= upper[r] && rows[r] >= lower[r])) return i;
      }
    }
    Map(out_q + i * nq, nq) = x.head(nq);
    Map(out_v + i * nv, nv) = x.tail(nv);
    Map(out_tau + i * nu, nu) = u;
    double* wrench = out_wrench + i * wrench_rows * 6;
    std::fill(wrench, wrench + wrench_rows * 6, 0.0);
    for (std::size_t j = 0; j < contacts.size(); ++j) {
      const auto& f = force_of[j]->f;
      Eigen::Map<Eigen::Vector3d> linear(wrench + contacts[j].row * 6), angular(wrench + contacts[j].row * 6 + 3);
      if (contacts[j].flat) {
        const Eigen::Matrix3d& rotation = dynamics->pinocchio.oMf[contacts[j].frame].rotation();
        linear = rotation * f.linear();
        angular = rotation * f.angular();
      } else {
        linear = f.linear();
      }
    }
    x = integrated->xnext;
    if (!x.allFinite()) return i + 1;
  }
  return count;
}

inline void expose() {
  bp::def("track_frames", &run,
          bp::args("fine", "fine_data", "state", "pointers", "first", "count", "kp", "kd", "frame_dt", "contacts",
                   "wrench_rows", "cone_rows", "cone_cols"),
          "The 200 Hz frames' tracking law over one node in C++ (opt2skill.trajopt.tracking); returns the index of "
          "the first frame not written.");
}

}  // namespace frame_tracking
