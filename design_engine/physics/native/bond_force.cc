// The bond map's energy and force (spec 5.1 and 5.3, design_engine.physics.energy with the
// default model: nonlinear ligament law and contact barrier) as XLA CPU custom calls, with the
// reverse of each: the product of the Hessian with a vector, and the same product's derivative
// with respect to the bond geometry and the material.
//
// The energy is the one of `energy.make_energy`; this file writes its gradient out by hand and
// gets every second derivative from that gradient by forward differentiation (a dual number
// carrying the direction of the product). Built and registered by `native/__init__.py`, tested
// against the JAX energy by tests/test_native_force.py.
//
// Layout (`Inputs`): q [nb, 3] (u, v, theta) per unit; per bond arms [n, 4] (arm1 x, y,
// arm2 x, y), void_ref [n, 2], r0 [n, 2], the ligament stiffnesses [n, 3] and the contact
// constants [n, 3], bond k joining units b1[k] and b2[k]. Engine units: mm, rad, mJ, N/mm,
// N mm/rad. Every call takes the lattice's constants first (b1, b2 and, for the whole force,
// r0), then the state and the per-bond arrays (force.py's `_custom_call`).

#include <cmath>
#include <cstdint>
#include <type_traits>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

#define INLINE inline __attribute__((always_inline))

namespace {

// ---- a dual number: value and the derivative along one direction ----
template <class T>
struct Dual {
  T v, d;
};
template <class T> INLINE T val(T x) { return x; }
template <class T> INLINE T val(const Dual<T>& x) { return x.v; }
template <class T> INLINE Dual<T> operator+(Dual<T> a, Dual<T> b) { return {a.v + b.v, a.d + b.d}; }
template <class T> INLINE Dual<T> operator-(Dual<T> a, Dual<T> b) { return {a.v - b.v, a.d - b.d}; }
template <class T> INLINE Dual<T> operator*(Dual<T> a, Dual<T> b) { return {a.v * b.v, a.d * b.v + a.v * b.d}; }
template <class T> INLINE Dual<T> operator/(Dual<T> a, Dual<T> b) {
  T q = a.v / b.v;
  return {q, (a.d - q * b.d) / b.v};
}
template <class T> INLINE Dual<T> operator-(Dual<T> a) { return {-a.v, -a.d}; }
template <class T> INLINE Dual<T> operator+(Dual<T> a, T b) { return {a.v + b, a.d}; }
template <class T> INLINE Dual<T> operator+(T a, Dual<T> b) { return {a + b.v, b.d}; }
template <class T> INLINE Dual<T> operator-(Dual<T> a, T b) { return {a.v - b, a.d}; }
template <class T> INLINE Dual<T> operator-(T a, Dual<T> b) { return {a - b.v, -b.d}; }
template <class T> INLINE Dual<T> operator*(Dual<T> a, T b) { return {a.v * b, a.d * b}; }
template <class T> INLINE Dual<T> operator*(T a, Dual<T> b) { return {a * b.v, a * b.d}; }
template <class T> INLINE Dual<T> operator/(Dual<T> a, T b) { return {a.v / b, a.d / b}; }
template <class T> INLINE Dual<T> operator/(T a, Dual<T> b) {
  T q = a / b.v;
  return {q, -q * b.d / b.v};
}
template <class T> INLINE Dual<T> sqrt_(Dual<T> a) {
  T s = std::sqrt(a.v);
  return {s, a.d / (T(2) * s)};
}
template <class T> INLINE T sqrt_(T a) { return std::sqrt(a); }
template <class T> INLINE T pick(bool c, T a, T b) { return c ? a : b; }
template <class T> INLINE Dual<T> pick(bool c, Dual<T> a, Dual<T> b) {
  return {c ? a.v : b.v, c ? a.d : b.d};
}
template <class T> INLINE Dual<T> lift(T v, T d) { return {v, d}; }

// ---- atan2 by octant reduction and a Taylor series (angles.atan2: within 2 ulp) ----
template <class T>
INLINE T atan2_value(T y, T x) {
  const T t1 = T(0.19891236737965800691), t3 = T(0.66817863791929891999),
          c1 = T(0.41421356237309504880);
  const T pi = T(M_PI);
  T ax = std::fabs(x), ay = std::fabs(y);
  T big = ax > ay ? ax : ay, small = ax > ay ? ay : ax;
  T t = small / (big > T(0) ? big : T(1));
  T c = t > t3 ? T(1) : (t > t1 ? c1 : T(0));
  T base = t > t3 ? pi / T(4) : (t > t1 ? pi / T(8) : T(0));
  T u = (t - c) / (T(1) + t * c), z = u * u;
  T s = T(1.0 / 25);
  s = s * z - T(1.0 / 23);
  s = s * z + T(1.0 / 21);
  s = s * z - T(1.0 / 19);
  s = s * z + T(1.0 / 17);
  s = s * z - T(1.0 / 15);
  s = s * z + T(1.0 / 13);
  s = s * z - T(1.0 / 11);
  s = s * z + T(1.0 / 9);
  s = s * z - T(1.0 / 7);
  s = s * z + T(1.0 / 5);
  s = s * z - T(1.0 / 3);
  T a = base + (u + u * z * s);
  a = ay > ax ? pi / T(2) - a : a;
  a = x < T(0) ? pi - a : a;
  return y < T(0) ? -a : a;
}
template <class T> INLINE T atan2_(T y, T x) { return atan2_value(y, x); }
template <class T> INLINE Dual<T> atan2_(Dual<T> y, Dual<T> x) {
  return {atan2_value(y.v, x.v), (x.v * y.d - y.v * x.d) / (x.v * x.v + y.v * y.v)};
}

// angles onto [-pi, pi) by floor, as energy.wrap (the floor's derivative is 0)
template <class S>
INLINE S wrap(S p) {
  using T = decltype(val(p));
  const T pi = T(M_PI);
  return p - T(2) * pi * std::floor((val(p) + pi) / (T(2) * pi));
}

// cos and sin of x, arithmetic only (vectorisable): x = k pi/2 + r, |r| <= pi/4, Taylor series
INLINE void sincos_(double x, double* c, double* s) {
  const double two_over_pi = 0.63661977236758134308;
  const double p1 = 1.5707963267341256e+00, p2 = 6.0771005065061922e-11,
               p3 = 2.0222662487959506e-21;  // pi/2 in three parts (Cody-Waite)
  double k = std::nearbyint(x * two_over_pi);
  double r = ((x - k * p1) - k * p2) - k * p3, z = r * r;
  double sr = r * (1 + z * (-1.0 / 6 + z * (1.0 / 120 + z * (-1.0 / 5040 + z * (1.0 / 362880 +
              z * (-1.0 / 39916800 + z * (1.0 / 6227020800.0 + z * (-1.0 / 1307674368000.0))))))));
  double cr = 1 + z * (-0.5 + z * (1.0 / 24 + z * (-1.0 / 720 + z * (1.0 / 40320 + z * (-1.0 / 3628800 +
              z * (1.0 / 479001600.0 + z * (-1.0 / 87178291200.0 + z * (1.0 / 20922789888000.0))))))));
  double q = k - 4.0 * std::floor(0.25 * k);  // the quadrant, 0-3, kept in floating point
  *s = q == 0 ? sr : (q == 1 ? cr : (q == 2 ? -sr : -cr));
  *c = q == 0 ? cr : (q == 1 ? -sr : (q == 2 ? -cr : sr));
}

// ---- the contact barrier of one void angle (energy.contact_energy) and its derivatives ----
// value C, dC/dalpha, dC/dk_contact, dC/dcontact_min, dC/dcontact_cutoff
template <class S, class T>
INLINE void barrier(S a, T kc, T tmin, T tcut, S* c, S* dc, S* dkc, S* dtmin, S* dtcut) {
  const bool active = (val(a) >= tmin) & (val(a) < tcut);
  const T span = tcut - tmin;
  S tau = pick(active, (a - tcut) / span, S{} + T(-0.5));
  S d = T(1) - tau * tau, d2 = d * d, tau2 = tau * tau;
  S unit = T(0.5) * span * span * tau2 / d;
  S slope = kc * span * tau / d2;
  S dspan = -kc * span * tau2 * tau2 / d2;  // dC/dspan at fixed alpha - cutoff
  const S zero = S{} + T(0);
  *c = pick(active, kc * unit, zero);
  *dc = pick(active, slope, zero);
  *dkc = pick(active, unit, zero);
  *dtmin = pick(active, -dspan, zero);
  *dtcut = pick(active, -slope + dspan, zero);
}

// ---- one bond: energy, gradient in the 6 DOFs of its two units, and (PARAMS) in its 12
// parameters (arm1 x, y, arm2 x, y, void_ref 1, 2, k_stretch, k_shear, k_bend, k_contact,
// contact_min, contact_cutoff) ----
template <bool PARAMS, class S, class T>
INLINE void bond(S u1, S v1, S th1, S u2, S v2, S th2, S hc1, S hs1, S hc2, S hs2, T a1x, T a1y,
                 T a2x, T a2y, T r0x, T r0y, T vr1, T vr2, T ks, T kh, T kb, T kc, T tmin, T tcut,
                 T l0, bool contact, S* e, S* g, S* gp) {
  // cos and sin of each end's rotation, and of the mean rotation, from the half angles
  S c1 = T(1) - T(2) * hs1 * hs1, s1 = T(2) * hs1 * hc1;
  S c2 = T(1) - T(2) * hs2 * hs2, s2 = T(2) * hs2 * hc2;
  S c1m = c1 - T(1), c2m = c2 - T(1);
  S w1x = u1 + c1m * a1x - s1 * a1y, w1y = v1 + s1 * a1x + c1m * a1y;
  S w2x = u2 + c2m * a2x - s2 * a2y, w2y = v2 + s2 * a2x + c2m * a2y;
  S ex = r0x + (w2x - w1x), ey = r0y + (w2y - w1y);
  S len2 = ex * ex + ey * ey, len = sqrt_(len2);
  S strain = len / l0 - T(1);
  S cm = hc1 * hc2 - hs1 * hs2, sm = hs1 * hc2 + hc1 * hs2;
  S cx = cm * r0x - sm * r0y, cy = sm * r0x + cm * r0y;
  S psi = atan2_(cx * ey - cy * ex, cx * ex + cy * ey);
  S bend = th2 - th1;
  S el = strain * l0, pl = psi * l0;
  *e = T(0.5) * ks * el * el + T(0.5) * kh * pl * pl + T(0.5) * kb * bend * bend;
  // dE/de: stretch along e, shear across it (d angle(e) / de = (-ey, ex) / |e|^2)
  S fs = ks * l0 * strain / len, fh = kh * l0 * pl / len2;
  S gex = fs * ex - fh * ey, gey = fs * ey + fh * ex;
  S half_shear = T(-0.5) * kh * l0 * pl;  // dE/dpsi dpsi/dtheta_i through the mean rotation
  // d node / d theta = R(theta) (-ay, ax)
  S p1x = -s1 * a1x - c1 * a1y, p1y = c1 * a1x - s1 * a1y;
  S p2x = -s2 * a2x - c2 * a2y, p2y = c2 * a2x - s2 * a2y;
  S dth1 = -(gex * p1x + gey * p1y) + half_shear - kb * bend;
  S dth2 = gex * p2x + gey * p2y + half_shear + kb * bend;
  S zero = S{} + T(0);
  S cv1 = zero, cd1 = zero, ck1 = zero, cmin1 = zero, ccut1 = zero;
  S cv2 = zero, cd2 = zero, ck2 = zero, cmin2 = zero, ccut2 = zero;
  if (contact) {
    barrier(wrap(vr1 - bend), kc, tmin, tcut, &cv1, &cd1, &ck1, &cmin1, &ccut1);
    barrier(wrap(vr2 + bend), kc, tmin, tcut, &cv2, &cd2, &ck2, &cmin2, &ccut2);
    *e = *e + cv1 + cv2;
    dth1 = dth1 + cd1 - cd2;  // alpha1 = ref1 - bend, alpha2 = ref2 + bend
    dth2 = dth2 - cd1 + cd2;
  }
  g[0] = -gex;
  g[1] = -gey;
  g[2] = dth1;
  g[3] = gex;
  g[4] = gey;
  g[5] = dth2;
  if constexpr (PARAMS) {
    // node 1 = centroid + u1 + R1 arm1, and e = r0 + w2 - w1
    gp[0] = -(gex * c1m + gey * s1);
    gp[1] = -(gey * c1m - gex * s1);
    gp[2] = gex * c2m + gey * s2;
    gp[3] = gey * c2m - gex * s2;
    gp[4] = cd1;
    gp[5] = cd2;
    gp[6] = T(0.5) * el * el;
    gp[7] = T(0.5) * pl * pl;
    gp[8] = T(0.5) * bend * bend;
    gp[9] = ck1 + ck2;
    gp[10] = cmin1 + cmin2;
    gp[11] = ccut1 + ccut2;
  }
}

template <ffi::DataType DT>
using Buf = ffi::Buffer<DT>;
template <ffi::DataType DT>
using Res = ffi::ResultBuffer<DT>;

// the bond map's inputs: unit indices of both ends [n], state [nb, 3], arms [n, 4], void_ref
// [n, 2], r0 [n, 2], ligament stiffnesses [n, 3] (k_stretch, k_shear, k_bend) and contact
// constants [n, 3] (k_contact, contact_min, contact_cutoff); the sizes checked once per call
template <ffi::DataType DT>
struct Inputs {
  const int32_t *i1, *i2;
  const ffi::NativeType<DT>*x, *arms, *vref, *r0, *lig, *con;
  int64_t nb, n;
};

template <ffi::DataType DT>
ffi::Error Read(Buf<ffi::S32> b1, Buf<ffi::S32> b2, Buf<DT> q, Buf<DT> arms, Buf<DT> vref,
                Buf<DT> r0, Buf<DT> lig, Buf<DT> con, Inputs<DT>* in) {
  const int64_t n = b1.element_count();
  if (b2.element_count() != n || arms.element_count() != 4 * n ||
      vref.element_count() != 2 * n || r0.element_count() != 2 * n ||
      lig.element_count() != 3 * n || con.element_count() != 3 * n ||
      q.element_count() % 3 != 0) {
    return ffi::Error::InvalidArgument("bond_force: inconsistent bond array sizes");
  }
  *in = {b1.typed_data(), b2.typed_data(), q.typed_data(), arms.typed_data(),
         vref.typed_data(), r0.typed_data(), lig.typed_data(), con.typed_data(),
         static_cast<int64_t>(q.element_count() / 3), n};
  for (int64_t k = 0; k < n; ++k) {
    if (in->i1[k] < 0 || in->i2[k] < 0 || in->i1[k] >= in->nb || in->i2[k] >= in->nb)
      return ffi::Error::InvalidArgument("bond_force: a bond's unit index is out of range");
  }
  return ffi::Error::Success();
}

// the per-bond state gathered from the units into contiguous arrays g [10, n] (u1, v1, th1,
// u2, v2, th2, and cos and sin of both half rotations) and, with `lam`, the direction of a
// Hessian product the same way, d [6, n]: the loop over the bonds then reads nothing by index
// and is vectorised. Returns g; d follows it in `work`
template <class T>
T* Gather(int64_t nb, int64_t n, const int32_t* i1, const int32_t* i2, const T* x,
          const T* lam, int64_t extra, std::vector<T>* work) {
  work->resize(2 * nb + (lam ? 16 : 10) * n + extra);
  T *hc = work->data(), *hs = hc + nb, *g = hs + nb;
  for (int64_t b = 0; b < nb; ++b) {
    double c, s;
    sincos_(0.5 * double(x[3 * b + 2]), &c, &s);
    hc[b] = T(c);
    hs[b] = T(s);
  }
  for (int64_t k = 0; k < n; ++k) {
    const int64_t i = i1[k], j = i2[k];
    for (int a = 0; a < 3; ++a) {
      g[a * n + k] = x[3 * i + a];
      g[(3 + a) * n + k] = x[3 * j + a];
    }
    g[6 * n + k] = hc[i];
    g[7 * n + k] = hs[i];
    g[8 * n + k] = hc[j];
    g[9 * n + k] = hs[j];
  }
  if (lam) {
    T* d = g + 10 * n;
    for (int64_t k = 0; k < n; ++k) {
      const int64_t i = i1[k], j = i2[k];
      for (int a = 0; a < 3; ++a) {
        d[a * n + k] = lam[3 * i + a];
        d[(3 + a) * n + k] = lam[3 * j + a];
      }
    }
  }
  return g;
}

// sums the bonds' gradients at their two ends p1, p2 [n, 3] (u, v, theta) onto the units
template <class T>
void Scatter(int64_t nb, int64_t n, const int32_t* i1, const int32_t* i2, const T* p1,
             const T* p2, T* out) {
  for (int64_t a = 0; a < 3 * nb; ++a) out[a] = T(0);
  for (int64_t k = 0; k < n; ++k) {
    const int64_t i = i1[k], j = i2[k];
    for (int a = 0; a < 3; ++a) {
      out[3 * i + a] += p1[3 * k + a];
      out[3 * j + a] += p2[3 * k + a];
    }
  }
}

// the bonds' energies pe [n] and gradients at their two ends p1, p2 [n, 3], from the gathered
// state g [10, n]. Every array a parameter of its own (restrict), and every group of
// interleaved values 2, 3 or 4 wide, so that GCC vectorises the loop
template <class T>
void ForwardLoop(int64_t n, const T* __restrict g, const T* __restrict ar,
                 const T* __restrict vr, const T* __restrict r, const T* __restrict ml,
                 const T* __restrict mc, T l0, bool with_contact, T* __restrict pe,
                 T* __restrict p1, T* __restrict p2) {
  for (int64_t k = 0; k < n; ++k) {
    T e, gq[6];
    bond<false>(g[k], g[n + k], g[2 * n + k], g[3 * n + k], g[4 * n + k], g[5 * n + k],
                g[6 * n + k], g[7 * n + k], g[8 * n + k], g[9 * n + k], ar[4 * k],
                ar[4 * k + 1], ar[4 * k + 2], ar[4 * k + 3], r[2 * k], r[2 * k + 1], vr[2 * k],
                vr[2 * k + 1], ml[3 * k], ml[3 * k + 1], ml[3 * k + 2], mc[3 * k],
                mc[3 * k + 1], mc[3 * k + 2], l0, with_contact, &e, gq,
                static_cast<T*>(nullptr));
    pe[k] = e;
    for (int a = 0; a < 3; ++a) {
      p1[3 * k + a] = gq[a];
      p2[3 * k + a] = gq[3 + a];
    }
  }
}

// the bonds' reverse, from the gathered state g [10, n] and direction d [6, n]: the
// cotangents of their two ends p1, p2 [n, 3], arms ab [n, 4], void angles vb [n, 2] and
// material lb, cb [n, 3]
template <class T>
void ReverseLoop(int64_t n, const T* __restrict g, const T* __restrict d,
                 const T* __restrict ar, const T* __restrict vr, const T* __restrict r,
                 const T* __restrict ml, const T* __restrict mc, T l0, bool with_contact,
                 T ebar, T* __restrict p1, T* __restrict p2, T* __restrict ab,
                 T* __restrict vb, T* __restrict lb, T* __restrict cb) {
  using D = Dual<T>;
  for (int64_t k = 0; k < n; ++k) {
    const T d1 = d[2 * n + k], d2 = d[5 * n + k];
    const T hc1 = g[6 * n + k], hs1 = g[7 * n + k], hc2 = g[8 * n + k], hs2 = g[9 * n + k];
    D e, gq[6], gp[12];
    bond<true>(lift(g[k], d[k]), lift(g[n + k], d[n + k]), lift(g[2 * n + k], d1),
               lift(g[3 * n + k], d[3 * n + k]), lift(g[4 * n + k], d[4 * n + k]),
               lift(g[5 * n + k], d2), lift(hc1, T(-0.5) * hs1 * d1),
               lift(hs1, T(0.5) * hc1 * d1), lift(hc2, T(-0.5) * hs2 * d2),
               lift(hs2, T(0.5) * hc2 * d2), ar[4 * k], ar[4 * k + 1], ar[4 * k + 2],
               ar[4 * k + 3], r[2 * k], r[2 * k + 1], vr[2 * k], vr[2 * k + 1], ml[3 * k],
               ml[3 * k + 1], ml[3 * k + 2], mc[3 * k], mc[3 * k + 1], mc[3 * k + 2], l0,
               with_contact, &e, gq, gp);
    for (int a = 0; a < 3; ++a) {
      p1[3 * k + a] = ebar * gq[a].v + gq[a].d;
      p2[3 * k + a] = ebar * gq[3 + a].v + gq[3 + a].d;
      lb[3 * k + a] = ebar * gp[6 + a].v + gp[6 + a].d;
      cb[3 * k + a] = ebar * gp[9 + a].v + gp[9 + a].d;
    }
    for (int a = 0; a < 4; ++a) ab[4 * k + a] = ebar * gp[a].v + gp[a].d;
    for (int a = 0; a < 2; ++a) vb[2 * k + a] = ebar * gp[4 + a].v + gp[4 + a].d;
  }
}

// energy and gradient [nb, 3] of the bond map at q
template <ffi::DataType DT>
ffi::Error Force(Buf<ffi::S32> b1, Buf<ffi::S32> b2, Buf<DT> r0, Buf<DT> q, Buf<DT> arms,
                 Buf<DT> vref, Buf<DT> lig, Buf<DT> con, Res<DT> energy, Res<DT> grad,
                 double l0, int32_t contact) {
  using T = ffi::NativeType<DT>;
  Inputs<DT> in;
  if (auto err = Read(b1, b2, q, arms, vref, r0, lig, con, &in); err.failure()) return err;
  const int64_t n = in.n;
  thread_local std::vector<T> work;
  T* g = Gather<T>(in.nb, n, in.i1, in.i2, in.x, nullptr, 7 * n, &work);
  T *pe = g + 10 * n, *p1 = pe + n, *p2 = p1 + 3 * n;
  ForwardLoop(n, g, in.arms, in.vref, in.r0, in.lig, in.con, T(l0), contact != 0, pe, p1, p2);
  T total = T(0);
  for (int64_t k = 0; k < n; ++k) total += pe[k];
  Scatter(in.nb, n, in.i1, in.i2, p1, p2, grad->typed_data());
  energy->typed_data()[0] = total;
  return ffi::Error::Success();
}

// reverse of Force: cotangents (ebar, gbar [nb, 3]) of (energy, gradient) -> cotangents of q,
// arms, void_ref and the two material arrays: ebar dE/dx + (d grad / dx)^T gbar
template <ffi::DataType DT>
ffi::Error ForceVjp(Buf<ffi::S32> b1, Buf<ffi::S32> b2, Buf<DT> r0, Buf<DT> q, Buf<DT> arms,
                    Buf<DT> vref, Buf<DT> lig, Buf<DT> con, Buf<DT> ebar, Buf<DT> gbar,
                    Res<DT> qbar, Res<DT> armsbar, Res<DT> vrefbar, Res<DT> ligbar,
                    Res<DT> conbar, double l0, int32_t contact) {
  using T = ffi::NativeType<DT>;
  Inputs<DT> in;
  if (auto err = Read(b1, b2, q, arms, vref, r0, lig, con, &in); err.failure()) return err;
  if (gbar.element_count() != q.element_count() || ebar.element_count() != 1)
    return ffi::Error::InvalidArgument("bond_force_vjp: cotangent sizes do not match");
  const int64_t n = in.n;
  thread_local std::vector<T> work;
  T* g = Gather<T>(in.nb, n, in.i1, in.i2, in.x, gbar.typed_data(), 6 * n, &work);
  T *d = g + 10 * n, *p1 = d + 6 * n, *p2 = p1 + 3 * n;
  ReverseLoop(n, g, d, in.arms, in.vref, in.r0, in.lig, in.con, T(l0), contact != 0,
              ebar.typed_data()[0], p1, p2, armsbar->typed_data(), vrefbar->typed_data(),
              ligbar->typed_data(), conbar->typed_data());
  Scatter(in.nb, n, in.i1, in.i2, p1, p2, qbar->typed_data());
  return ffi::Error::Success();
}

// ---- the contact terms alone, from the units' rotations (the fast force of a split step,
// energy.make_contact_energy): theta [m], bonds joining entries b1[k] and b2[k] of theta ----

template <ffi::DataType DT>
ffi::Error ReadContact(Buf<ffi::S32> b1, Buf<ffi::S32> b2, Buf<DT> theta, Buf<DT> vref,
                       Buf<DT> con, int64_t* n) {
  *n = b1.element_count();
  const int64_t m = theta.element_count();
  if (b2.element_count() != *n || vref.element_count() != 2 * *n || con.element_count() != 3 * *n)
    return ffi::Error::InvalidArgument("contact_force: inconsistent bond array sizes");
  for (int64_t k = 0; k < *n; ++k) {
    const int32_t i = b1.typed_data()[k], j = b2.typed_data()[k];
    if (i < 0 || j < 0 || i >= m || j >= m)
      return ffi::Error::InvalidArgument("contact_force: a bond's rotation index is out of range");
  }
  return ffi::Error::Success();
}

// the bonds' contact energies pe [n] and d energy / d bend pb [n] (bend = theta[b2] - theta[b1],
// gathered into bend [n]); with the direction of a Hessian product db [n], PARAMS gives the
// reverse: pb = ebar dE/dbend + d2E/dbend2 db, and the cotangents of vref vb [n, 2] and of the
// contact constants cb [n, 3]
template <bool PARAMS, class T>
void ContactLoop(int64_t n, const T* __restrict bend, const T* __restrict db,
                 const T* __restrict vr, const T* __restrict mc, T ebar, T* __restrict pe,
                 T* __restrict pb, T* __restrict vb, T* __restrict cb) {
  using S = std::conditional_t<PARAMS, Dual<T>, T>;
  for (int64_t k = 0; k < n; ++k) {
    S b;
    if constexpr (PARAMS) {
      b = lift(bend[k], db[k]);
    } else {
      b = bend[k];
    }
    S c1, d1, k1, lo1, hi1, c2, d2, k2, lo2, hi2;
    barrier(wrap(vr[2 * k] - b), mc[3 * k], mc[3 * k + 1], mc[3 * k + 2], &c1, &d1, &k1, &lo1,
            &hi1);
    barrier(wrap(vr[2 * k + 1] + b), mc[3 * k], mc[3 * k + 1], mc[3 * k + 2], &c2, &d2, &k2,
            &lo2, &hi2);
    S slope = d2 - d1;  // alpha1 = ref1 - bend, alpha2 = ref2 + bend
    if constexpr (PARAMS) {
      pb[k] = ebar * slope.v + slope.d;
      vb[2 * k] = ebar * d1.v + d1.d;
      vb[2 * k + 1] = ebar * d2.v + d2.d;
      S kk = k1 + k2, lo = lo1 + lo2, hi = hi1 + hi2;
      cb[3 * k] = ebar * kk.v + kk.d;
      cb[3 * k + 1] = ebar * lo.v + lo.d;
      cb[3 * k + 2] = ebar * hi.v + hi.d;
    } else {
      pe[k] = c1 + c2;
      pb[k] = slope;
    }
  }
}

// gathers bend [n] (and with lam [m], its direction [n]) into work; returns bend
template <class T>
T* GatherBend(int64_t n, const int32_t* i1, const int32_t* i2, const T* th, const T* lam,
              int64_t extra, std::vector<T>* work) {
  work->resize((lam ? 2 : 1) * n + extra);
  T* bend = work->data();
  for (int64_t k = 0; k < n; ++k) bend[k] = th[i2[k]] - th[i1[k]];
  if (lam) {
    for (int64_t k = 0; k < n; ++k) bend[n + k] = lam[i2[k]] - lam[i1[k]];
  }
  return bend;
}

template <class T>
void ScatterBend(int64_t m, int64_t n, const int32_t* i1, const int32_t* i2, const T* pb, T* out) {
  for (int64_t a = 0; a < m; ++a) out[a] = T(0);
  for (int64_t k = 0; k < n; ++k) {
    out[i1[k]] -= pb[k];
    out[i2[k]] += pb[k];
  }
}

// contact energy and its gradient [m] in the rotations
template <ffi::DataType DT>
ffi::Error ContactForce(Buf<ffi::S32> b1, Buf<ffi::S32> b2, Buf<DT> theta, Buf<DT> vref,
                        Buf<DT> con, Res<DT> energy, Res<DT> grad) {
  using T = ffi::NativeType<DT>;
  int64_t n;
  if (auto err = ReadContact(b1, b2, theta, vref, con, &n); err.failure()) return err;
  const int32_t *i1 = b1.typed_data(), *i2 = b2.typed_data();
  thread_local std::vector<T> work;
  T* bend = GatherBend<T>(n, i1, i2, theta.typed_data(), nullptr, 2 * n, &work);
  T *pe = bend + n, *pb = pe + n;
  ContactLoop<false>(n, bend, static_cast<const T*>(nullptr), vref.typed_data(),
                     con.typed_data(), T(0), pe, pb, static_cast<T*>(nullptr),
                     static_cast<T*>(nullptr));
  T total = T(0);
  for (int64_t k = 0; k < n; ++k) total += pe[k];
  ScatterBend(theta.element_count(), n, i1, i2, pb, grad->typed_data());
  energy->typed_data()[0] = total;
  return ffi::Error::Success();
}

// reverse of ContactForce: (ebar, gbar [m]) -> cotangents of theta, vref and the constants
template <ffi::DataType DT>
ffi::Error ContactForceVjp(Buf<ffi::S32> b1, Buf<ffi::S32> b2, Buf<DT> theta, Buf<DT> vref,
                           Buf<DT> con, Buf<DT> ebar, Buf<DT> gbar, Res<DT> thetabar,
                           Res<DT> vrefbar, Res<DT> conbar) {
  using T = ffi::NativeType<DT>;
  int64_t n;
  if (auto err = ReadContact(b1, b2, theta, vref, con, &n); err.failure()) return err;
  if (gbar.element_count() != theta.element_count() || ebar.element_count() != 1)
    return ffi::Error::InvalidArgument("contact_force_vjp: cotangent sizes do not match");
  const int32_t *i1 = b1.typed_data(), *i2 = b2.typed_data();
  thread_local std::vector<T> work;
  T* bend = GatherBend<T>(n, i1, i2, theta.typed_data(), gbar.typed_data(), n, &work);
  T* pb = bend + 2 * n;
  ContactLoop<true>(n, bend, bend + n, vref.typed_data(), con.typed_data(),
                    ebar.typed_data()[0], static_cast<T*>(nullptr), pb, vrefbar->typed_data(),
                    conbar->typed_data());
  ScatterBend(theta.element_count(), n, i1, i2, pb, thetabar->typed_data());
  return ffi::Error::Success();
}

}  // namespace

#define BOND_FORCE_ARGS(DT)                                                           \
  ffi::Ffi::Bind()                                                                    \
      .Arg<Buf<ffi::S32>>()                                                           \
      .Arg<Buf<ffi::S32>>()                                                           \
      .Arg<Buf<DT>>()                                                                 \
      .Arg<Buf<DT>>()                                                                 \
      .Arg<Buf<DT>>()                                                                 \
      .Arg<Buf<DT>>()                                                                 \
      .Arg<Buf<DT>>()                                                                 \
      .Arg<Buf<DT>>()

#define BOND_FORCE(DT)                                                                \
  BOND_FORCE_ARGS(DT)                                                                 \
      .Ret<Buf<DT>>()                                                                 \
      .Ret<Buf<DT>>()                                                                 \
      .Attr<double>("l0")                                                             \
      .Attr<int32_t>("contact")

#define BOND_FORCE_VJP(DT)                                                            \
  BOND_FORCE_ARGS(DT)                                                                 \
      .Arg<Buf<DT>>()                                                                 \
      .Arg<Buf<DT>>()                                                                 \
      .Ret<Buf<DT>>()                                                                 \
      .Ret<Buf<DT>>()                                                                 \
      .Ret<Buf<DT>>()                                                                 \
      .Ret<Buf<DT>>()                                                                 \
      .Ret<Buf<DT>>()                                                                 \
      .Attr<double>("l0")                                                             \
      .Attr<int32_t>("contact")

XLA_FFI_DEFINE_HANDLER_SYMBOL(MetarigBondForceF64, Force<ffi::F64>, BOND_FORCE(ffi::F64));
XLA_FFI_DEFINE_HANDLER_SYMBOL(MetarigBondForceF32, Force<ffi::F32>, BOND_FORCE(ffi::F32));
XLA_FFI_DEFINE_HANDLER_SYMBOL(MetarigBondForceVjpF64, ForceVjp<ffi::F64>, BOND_FORCE_VJP(ffi::F64));
XLA_FFI_DEFINE_HANDLER_SYMBOL(MetarigBondForceVjpF32, ForceVjp<ffi::F32>, BOND_FORCE_VJP(ffi::F32));

#define CONTACT_FORCE_ARGS(DT) \
  ffi::Ffi::Bind().Arg<Buf<ffi::S32>>().Arg<Buf<ffi::S32>>().Arg<Buf<DT>>().Arg<Buf<DT>>().Arg<Buf<DT>>()
#define CONTACT_FORCE(DT) CONTACT_FORCE_ARGS(DT).Ret<Buf<DT>>().Ret<Buf<DT>>()
#define CONTACT_FORCE_VJP(DT) \
  CONTACT_FORCE_ARGS(DT).Arg<Buf<DT>>().Arg<Buf<DT>>().Ret<Buf<DT>>().Ret<Buf<DT>>().Ret<Buf<DT>>()

XLA_FFI_DEFINE_HANDLER_SYMBOL(MetarigContactForceF64, ContactForce<ffi::F64>, CONTACT_FORCE(ffi::F64));
XLA_FFI_DEFINE_HANDLER_SYMBOL(MetarigContactForceF32, ContactForce<ffi::F32>, CONTACT_FORCE(ffi::F32));
XLA_FFI_DEFINE_HANDLER_SYMBOL(MetarigContactForceVjpF64, ContactForceVjp<ffi::F64>,
                              CONTACT_FORCE_VJP(ffi::F64));
XLA_FFI_DEFINE_HANDLER_SYMBOL(MetarigContactForceVjpF32, ContactForceVjp<ffi::F32>,
                              CONTACT_FORCE_VJP(ffi::F32));
