// The bond map's kernels shared by the custom calls (bond_force.cc) and the native step
// (verlet_stages.cc): the energy and gradient of one bond, its forward-mode derivative, and the
// loops that gather the units' state onto the bonds, run every bond and scatter back. Layout
// and units: see bond_force.cc.

#pragma once

#include <cmath>
#include <cstdint>
#include <type_traits>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

#define INLINE inline __attribute__((always_inline))
#define NOINLINE __attribute__((noinline))

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

// whether every bond joins two units of the nb there are (each call checks its indices once)
INLINE bool BondsInRange(int64_t n, int64_t nb, const int32_t* i1, const int32_t* i2) {
  for (int64_t k = 0; k < n; ++k) {
    if (i1[k] < 0 || i2[k] < 0 || i1[k] >= nb || i2[k] >= nb) return false;
  }
  return true;
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
// CONTACT a template parameter: a condition on a run-time flag inside the loop stops GCC
// vectorising it
template <bool CONTACT, class T>
void ForwardLoop(int64_t n, const T* __restrict g, const T* __restrict ar,
                 const T* __restrict vr, const T* __restrict r, const T* __restrict ml,
                 const T* __restrict mc, T l0, T* __restrict pe,
                 T* __restrict p1, T* __restrict p2) {

  for (int64_t k = 0; k < n; ++k) {
    T e, gq[6];
    bond<false>(g[k], g[n + k], g[2 * n + k], g[3 * n + k], g[4 * n + k], g[5 * n + k],
                g[6 * n + k], g[7 * n + k], g[8 * n + k], g[9 * n + k], ar[4 * k],
                ar[4 * k + 1], ar[4 * k + 2], ar[4 * k + 3], r[2 * k], r[2 * k + 1], vr[2 * k],
                vr[2 * k + 1], ml[3 * k], ml[3 * k + 1], ml[3 * k + 2], mc[3 * k],
                mc[3 * k + 1], mc[3 * k + 2], l0, CONTACT, &e, gq,
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
template <bool CONTACT, class T>
void ReverseLoop(int64_t n, const T* __restrict g, const T* __restrict d,
                 const T* __restrict ar, const T* __restrict vr, const T* __restrict r,
                 const T* __restrict ml, const T* __restrict mc, T l0,
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
               CONTACT, &e, gq, gp);
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

// the bond map's energy at x [nb, 3] (returned) and its gradient grad [nb, 3]. A function of its
// own, called by every custom call
template <class T>
NOINLINE T BondForce(int64_t nb, int64_t n, const int32_t* i1, const int32_t* i2, const T* x,
                     const T* arms, const T* vref, const T* r0, const T* lig, const T* con, T l0,
                     bool contact, T* grad) {
  thread_local std::vector<T> work;
  T* g = Gather<T>(nb, n, i1, i2, x, nullptr, 7 * n, &work);
  T *pe = g + 10 * n, *p1 = pe + n, *p2 = p1 + 3 * n;
  if (contact) {
    ForwardLoop<true>(n, g, arms, vref, r0, lig, con, l0, pe, p1, p2);
  } else {
    ForwardLoop<false>(n, g, arms, vref, r0, lig, con, l0, pe, p1, p2);
  }
  T total = T(0);
  for (int64_t k = 0; k < n; ++k) total += pe[k];
  Scatter(nb, n, i1, i2, p1, p2, grad);
  return total;
}

// the reverse of BondForce: cotangents ebar, gbar [nb, 3] of (energy, gradient) -> cotangents
// of x (xbar [nb, 3]), arms [n, 4], void_ref [n, 2] and the two material arrays [n, 3]: ebar
// dE/dx + (d grad / dx)^T gbar
template <class T>
NOINLINE void BondForceVjp(int64_t nb, int64_t n, const int32_t* i1, const int32_t* i2,
                           const T* x, const T* arms, const T* vref, const T* r0, const T* lig,
                           const T* con, T l0, bool contact, T ebar, const T* gbar, T* xbar,
                           T* armsbar, T* vrefbar, T* ligbar, T* conbar) {
  thread_local std::vector<T> work;
  T* g = Gather<T>(nb, n, i1, i2, x, gbar, 6 * n, &work);
  T *d = g + 10 * n, *p1 = d + 6 * n, *p2 = p1 + 3 * n;
  if (contact) {
    ReverseLoop<true>(n, g, d, arms, vref, r0, lig, con, l0, ebar, p1, p2, armsbar, vrefbar,
                      ligbar, conbar);
  } else {
    ReverseLoop<false>(n, g, d, arms, vref, r0, lig, con, l0, ebar, p1, p2, armsbar, vrefbar,
                       ligbar, conbar);
  }
  Scatter(nb, n, i1, i2, p1, p2, xbar);
}

}  // namespace
