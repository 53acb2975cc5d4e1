// ctypes driver for benchmarks/peer_cpp.py: the forward problem of H. Gilbert's C++ CTR
// kinematics templates (github.com/medlabprojects/ConcentricTubeMexLibrary,
// ReferenceCannulaKinematics/) behind a small C interface.
//
// The peer integrates the standard Kirchhoff-rod model with torsion as ONE initial value problem
// from the tip angles PsiL to the tube bases (CTR::Kinematics) and can return
//   Zta = d(psi, m_z)(base) / d(PsiL, Beta)            (Option::ComputeZta)
//   Jb  = GetTipJacobianForTube1(y): the body-frame tip twist per (PsiL, Beta)  (ComputeJacobian)
// The forward problem (given the base rotations alpha) is shooting on PsiL: Newton with the
// top-left N x N block of Zta (with a backtracking line search: plain Newton diverges from
// PsiL = alpha on the Fig. 3 robot), until max_j |psi_j(base) - alpha_j| < tol.
//
// The actuator tip Jacobian is obtained as the library's own GetTipComplianceForTube1 eliminates
// PsiL (a Schur complement through Zta): along the solution manifold psi(base)(PsiL, Beta) = alpha,
//   dPsiL = Zpp^-1 (dalpha - Zpb dBeta),
//   J_act = [Jb_psi Zpp^-1 | Jb_beta - Jb_psi Zpp^-1 Zpb]       (body frame, per (alpha, Beta))
// and then rotated to the base frame with the tip rotation (R_tip, as the peer's fwkin_*.m do).
//
// Conventions of the peer (all arrays here): innermost tube first; Beta_j = -D_j; L = total
// length, Lt = straight (transmission) length; precurvature (kx, ky) constant over the curved
// part. Its precurvature is smoothed over a width (1 mm hard-wired in Tube's constructor); the
// width is set here by rebuilding the tube's private curvature mask (see set_smoothing).
//
// Build (benchmarks/peer_cpp.py does it): g++ -O3 -DNDEBUG -march=native -std=c++17 -fPIC -shared
//   -include iterator -I<peer>/ReferenceCannulaKinematics -I/usr/include/eigen3
//   driver.cpp <peer>/Rk8_Coeffs.cpp <peer>/TaggedInterval.cpp -o libpeer_cpp.so

#include <cmath>
#include <new>
#include <tuple>
#include <Eigen/Dense>

#include "BasicFunctions.h"
#include "Tube.h"
#include "Kinematics.h"
#include "Utility.h"

using namespace CTR;
using namespace CTR::Functions;

typedef constant_fun<Eigen::Vector2d> CurvFun;
typedef Tube<CurvFun> TubeT;

// --- access to Tube's private curvature mask (the standard explicit-instantiation idiom) ---------
namespace {
template <typename Tag, typename Tag::type M>
struct private_member {
   friend typename Tag::type get_member(Tag) { return M; }
};
struct uchi_tag {
   typedef mollified_indicator_fun<double> TubeT::*type;
   friend type get_member(uchi_tag);
};
struct duchi_tag {
   typedef mollified_indicator_fun_der<double> TubeT::*type;
   friend type get_member(duchi_tag);
};
}  // namespace
template struct private_member<uchi_tag, &TubeT::m_uChi>;
template struct private_member<duchi_tag, &TubeT::m_DuChi>;

// Replace the 1 mm smoothing of the precurvature at both ends of the curved part by `width`.
static void set_smoothing(TubeT &t, double L, double Lt, double width)
{
   mollified_indicator_fun<double> &u = t.*get_member(uchi_tag());
   u = mollified_indicator_fun<double>(Lt, L, width);
   mollified_indicator_fun_der<double> &du = t.*get_member(duchi_tag());
   du.~mollified_indicator_fun_der<double>();  // const members: rebuild in place
   new (&du) mollified_indicator_fun_der<double>(u);
}

// --- the solver ------------------------------------------------------------------------------------
template <int N> struct CannulaOf;
template <> struct CannulaOf<2> { typedef std::tuple<TubeT, TubeT> type; };
template <> struct CannulaOf<3> { typedef std::tuple<TubeT, TubeT, TubeT> type; };

template <int N>
struct Config {
   Eigen::Matrix<double, N, 1> PsiL;
   Eigen::Matrix<double, N, 1> Beta;
};

struct PeerBase {
   virtual ~PeerBase() {}
   virtual void eval(const double *psiL, const double *beta, double *psi_base, double *zta,
                     double *tip) const = 0;
   virtual int solve_many(int m, const double *alpha, const double *beta, const double *psi0,
                          double tol, int max_iter, int strategy, double *tip, double *jac,
                          double *psi_out, int *iters, int *evals, double *stab) const = 0;
};

template <int N>
struct Peer : PeerBase {
   typedef typename CannulaOf<N>::type Cannula;
   typedef Eigen::Matrix<double, N, 1> VecN;
   typedef Eigen::Matrix<double, N, N> MatN;
   typedef typename DeclareOptions<Option::ComputeZta>::options OTorsion;
   typedef typename DeclareOptions<Option::ComputeGeometry, Option::ComputeZta>::options OGeom;
   typedef typename DeclareOptions<Option::ComputeGeometry, Option::ComputeJacobian>::options OJac;

   Cannula C;

   explicit Peer(const Cannula &c) : C(c) {}

   // Newton on PsiL with options O, with a backtracking line search on |r|^2 (full steps from a
   // warm start cost nothing extra: the accepted trial integration is the next iterate). On
   // return q.PsiL is the solution and `ret` its integration; `evals` counts integrations.
   // Returns the Newton steps taken, or -1 (no convergence in max_iter steps / no descent).
   template <typename O>
   int shoot(Config<N> &q, const VecN &alpha, double tol, int max_iter,
             KinRet<State<N, O> > &ret, int &evals) const
   {
      ret = Kinematics(C, q, O(), 0, 0.0);
      evals = 1;
      VecN r = ret.y_final.Psi - alpha;
      for (int it = 0;; ++it) {
         double e = r.cwiseAbs().maxCoeff();
         if (!std::isfinite(e)) return -1;
         if (e < tol) return it;
         if (it == max_iter) return -1;
         MatN Zpp = ret.y_final.Zta.template topLeftCorner<N, N>();
         VecN d = -(Zpp.inverse() * r);
         double f = r.squaredNorm(), lam = 1.0;
         Config<N> qt = q;
         for (;;) {
            qt.PsiL = q.PsiL + lam * d;
            KinRet<State<N, O> > rt = Kinematics(C, qt, O(), 0, 0.0);
            ++evals;
            VecN rr = rt.y_final.Psi - alpha;
            double ft = rr.squaredNorm();
            if (std::isfinite(ft) && ft <= (1.0 - 2e-4 * lam) * f) {
               q = qt;
               ret = rt;
               r = rr;
               break;
            }
            lam *= 0.5;
            if (lam < 1e-6) return -1;
         }
      }
   }

   template <typename S>
   static double det_zpp(const KinRet<S> &r)
   {
      return r.y_final.Zta.template topLeftCorner<N, N>().determinant();
   }

   template <typename S>
   static void jacobian_out(const KinRet<S> &ret, double *jac)
   {
      // jac: 6 x 2N row-major, base frame, columns (alpha_0..alpha_N-1, Beta_0..Beta_N-1).
      Eigen::Matrix<double, 6, 2 * N> Jb = GetTipJacobianForTube1(ret.y_final);
      MatN Zpp = ret.y_final.Zta.template topLeftCorner<N, N>();
      MatN Zpb = ret.y_final.Zta.template topRightCorner<N, N>();
      MatN Zinv = Zpp.inverse();
      Eigen::Matrix<double, 6, 2 * N> Ja;
      Ja.template leftCols<N>() = Jb.template leftCols<N>() * Zinv;
      Ja.template rightCols<N>() = Jb.template rightCols<N>() - Jb.template leftCols<N>() * Zinv * Zpb;
      Eigen::Matrix3d R = Utility::quaternion_to_rotation_matrix(ret.qTip);
      Eigen::Matrix<double, 6, 2 * N> Js;
      Js.template topRows<3>() = R * Ja.template topRows<3>();
      Js.template bottomRows<3>() = R * Ja.template bottomRows<3>();
      for (int i = 0; i < 6; ++i)
         for (int j = 0; j < 2 * N; ++j) jac[i * 2 * N + j] = Js(i, j);
   }

   // One integration at PsiL: psi(base), Zta (2N x 2N row-major), tip.
   void eval(const double *psiL, const double *beta, double *psi_base, double *zta,
             double *tip) const override
   {
      Config<N> q;
      for (int j = 0; j < N; ++j) { q.PsiL(j) = psiL[j]; q.Beta(j) = beta[j]; }
      KinRet<State<N, OGeom> > r = Kinematics(C, q, OGeom(), 0, 0.0);
      for (int j = 0; j < N; ++j) psi_base[j] = r.y_final.Psi(j);
      for (int i = 0; i < 2 * N; ++i)
         for (int j = 0; j < 2 * N; ++j) zta[i * 2 * N + j] = r.y_final.Zta(i, j);
      for (int i = 0; i < 3; ++i) tip[i] = r.pTip(i);
   }

   // strategy 0: solve, geometry + Zta in every Newton integration (the converged one gives the tip)
   //          1: solve, Zta only while iterating, then one geometry integration at the solution
   //          2: solve + Jacobian, Jacobian options (geometry, Zga, Zta) in every integration
   //          3: solve + Jacobian, geometry + Zta while iterating, then one Jacobian integration
   //          4: solve + Jacobian, Zta only while iterating, then one Jacobian integration
   int solve_many(int m, const double *alpha, const double *beta, const double *psi0, double tol,
                  int max_iter, int strategy, double *tip, double *jac, double *psi_out,
                  int *iters, int *evals, double *stab) const override
   {
      int failures = 0;
      for (int k = 0; k < m; ++k) {
         Config<N> q;
         VecN a;
         for (int j = 0; j < N; ++j) {
            a(j) = alpha[k * N + j];
            q.Beta(j) = beta[k * N + j];
            q.PsiL(j) = psi0[k * N + j];
         }
         int n = -1, ne = 0;
         double st = NAN;
         Eigen::Vector3d p = Eigen::Vector3d::Constant(NAN);
         if (strategy == 0) {
            KinRet<State<N, OGeom> > r;
            n = shoot(q, a, tol, max_iter, r, ne);
            if (stab) st = det_zpp(r);
            p = r.pTip;
         } else if (strategy == 1) {
            KinRet<State<N, OTorsion> > r;
            n = shoot(q, a, tol, max_iter, r, ne);
            if (stab) st = det_zpp(r);
            if (n >= 0) p = Kinematics(C, q, OGeom(), 0, 0.0).pTip;
         } else if (strategy == 2) {
            KinRet<State<N, OJac> > r;
            n = shoot(q, a, tol, max_iter, r, ne);
            if (stab) st = det_zpp(r);
            p = r.pTip;
            if (jac) jacobian_out(r, jac + k * 12 * N);
         } else if (strategy == 3 || strategy == 4) {
            if (strategy == 3) {
               KinRet<State<N, OGeom> > r;
               n = shoot(q, a, tol, max_iter, r, ne);
            if (stab) st = det_zpp(r);
            } else {
               KinRet<State<N, OTorsion> > r;
               n = shoot(q, a, tol, max_iter, r, ne);
            if (stab) st = det_zpp(r);
            }
            if (n >= 0) {
               KinRet<State<N, OJac> > r = Kinematics(C, q, OJac(), 0, 0.0);
               p = r.pTip;
               if (jac) jacobian_out(r, jac + k * 12 * N);
            }
         } else {
            return -1000;
         }
         if (n < 0) ++failures;
         if (strategy == 1 || strategy >= 3) ne += (n >= 0);   // the final integration
         if (iters) iters[k] = n;
         if (evals) evals[k] = ne;
         if (stab) stab[k] = st;
         if (tip) for (int i = 0; i < 3; ++i) tip[k * 3 + i] = p(i);
         if (psi_out) for (int j = 0; j < N; ++j) psi_out[k * N + j] = q.PsiL(j);
      }
      return failures;
   }
};

// --- C interface -----------------------------------------------------------------------------------
extern "C" {

int peer_abi_version() { return 2; }

// Arrays of n tubes, innermost first. Returns NULL for an unsupported n (2 or 3 tubes).
void *peer_create(int n, const double *L, const double *Lt, const double *OD, const double *ID,
                  const double *kx, const double *ky, const double *E, const double *G,
                  double smoothing)
{
   if (n != 2 && n != 3) return nullptr;
   // Tubes are copy-constructed throughout: Tube's move assignment skips the curvature
   // derivatives, so never default-construct and assign one.
   auto tube = [&](int j) {
      TubeT t = make_annular_tube(L[j], Lt[j], OD[j], ID[j], CurvFun(Eigen::Vector2d(kx[j], ky[j])),
                                  E[j], G[j]);
      set_smoothing(t, L[j], Lt[j], smoothing > 0 ? smoothing : 1.0e-3);
      return t;
   };
   if (n == 2) return static_cast<PeerBase *>(new Peer<2>(Peer<2>::Cannula(tube(0), tube(1))));
   return static_cast<PeerBase *>(new Peer<3>(Peer<3>::Cannula(tube(0), tube(1), tube(2))));
}

// One integration (diagnostics): psi(base) n, Zta 2n x 2n, tip 3, at PsiL and Beta (n each).
void peer_eval(void *h, const double *psiL, const double *beta, double *psi_base, double *zta,
               double *tip)
{
   static_cast<PeerBase *>(h)->eval(psiL, beta, psi_base, zta, tip);
}

void peer_destroy(void *h) { delete static_cast<PeerBase *>(h); }

// m configurations (arrays m x n, innermost first): base rotations alpha, Beta = -D, Newton start
// psi0 (PsiL). Outputs (any may be NULL): tip m x 3 [m] (base frame at the orifice), jac m x 6 x 2n
// (strategies 2-4), psi_out m x n (the solution PsiL), iters m (Newton steps, -1 = failed),
// evals m (IVP integrations, the final geometry/Jacobian one included), stab m (the library's
// stability measure GetStability: det(d psi(base) / d PsiL) at the solution, > 0 on the stable
// branch grown from the straight configuration, changing sign where stability is lost).
// Returns the number of failed solves (-1000: bad strategy).
int peer_solve_many(void *h, int m, const double *alpha, const double *beta, const double *psi0,
                    double tol, int max_iter, int strategy, double *tip, double *jac,
                    double *psi_out, int *iters, int *evals, double *stab)
{
   return static_cast<PeerBase *>(h)->solve_many(m, alpha, beta, psi0, tol, max_iter, strategy,
                                                tip, jac, psi_out, iters, evals, stab);
}
}
