// The bond map's energy and force (spec 5.1 and 5.3, design_engine.physics.energy with the
// default model: nonlinear ligament law and contact barrier) as XLA CPU custom calls, with the
// reverse of each: the product of the Hessian with a vector, and the same product's derivative
// with respect to the bond geometry and the material.
//
// The energy is the one of `energy.make_energy`; bond_kernels.h writes its gradient out by hand
// and gets every second derivative from that gradient by forward differentiation (a dual number
// carrying the direction of the product); this file wraps it as custom calls. Built and
// registered by `build.py`, tested against the JAX energy by tests/test_native_force.py.
//
// Layout (`Inputs`): q [nb, 3] (u, v, theta) per unit; per bond arms [n, 4] (arm1 x, y,
// arm2 x, y), void_ref [n, 2], r0 [n, 2], the ligament stiffnesses [n, 3] and the contact
// constants [n, 3], bond k joining units b1[k] and b2[k]. Engine units: mm, rad, mJ, N/mm,
// N mm/rad. Every call takes the lattice's constants first (b1, b2 and, for the whole force,
// r0), then the state and the per-bond arrays (force.py's `_custom_call`).

#include "bond_kernels.h"

namespace {

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
  if (!BondsInRange(n, in->nb, in->i1, in->i2))
    return ffi::Error::InvalidArgument("bond_force: a bond's unit index is out of range");
  return ffi::Error::Success();
}

// energy and gradient [nb, 3] of the bond map at q
template <ffi::DataType DT>
ffi::Error Force(Buf<ffi::S32> b1, Buf<ffi::S32> b2, Buf<DT> r0, Buf<DT> q, Buf<DT> arms,
                 Buf<DT> vref, Buf<DT> lig, Buf<DT> con, Res<DT> energy, Res<DT> grad,
                 double l0, int32_t contact) {
  using T = ffi::NativeType<DT>;
  Inputs<DT> in;
  if (auto err = Read(b1, b2, q, arms, vref, r0, lig, con, &in); err.failure()) return err;
  const T total = BondForce(in.nb, in.n, in.i1, in.i2, in.x, in.arms, in.vref, in.r0, in.lig,
                            in.con, T(l0), contact != 0, grad->typed_data());
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
  BondForceVjp(in.nb, in.n, in.i1, in.i2, in.x, in.arms, in.vref, in.r0, in.lig, in.con, T(l0),
               contact != 0, ebar.typed_data()[0], gbar.typed_data(), qbar->typed_data(),
               armsbar->typed_data(), vrefbar->typed_data(), ligbar->typed_data(),
               conbar->typed_data());
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
