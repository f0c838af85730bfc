// A composition of velocity Verlet stages under the bond map's force, in one XLA CPU custom
// call, with its reverse: the fixed-step schemes of `solve.fixed_step` (one stage, Verlet; five,
// Suzuki's fourth order) for the native force without a split contact step.
//
// Stage k of length h[k] from (q, v, f): v_half = v + h/2 M^-1 (f - C v), q1 = q + h v_half,
// f1 = -dV/dq_f at q1 (the prescribed units at qc[k]), v1 = (v_half + h/2 M^-1 f1) / (1 + h/2
// M^-1 C), and the work-energy ledger of `fixed_step.ledger_step` (its inputs not
// differentiated). The same arithmetic as `fixed_step.integrate`'s Verlet step; here the
// stages' gathers, kicks and ledger run in one loop instead of some 25 XLA kernels a stage.
//
// Layout: the free state q, v, f, inverse mass and damping [nf]; the prescribed units' values
// qc and velocities qcd [m, nc] at the end of each of the m stages; `slot` [3 nb] gives, for
// every global DOF (unit-major u, v, theta), its index in [q_f, q_c]. Bond arrays as in
// bond_force.cc. The forward call returns the stage forces fs [m, nf] (the last is the step's
// force), kept by the reverse, which rebuilds the stages from them without evaluating a force
// and chains the Hessian products of bond_kernels.h. Tested against the JAX step, and its
// reverse against central differences, by tests/test_native_force.py.

#include <algorithm>

#include "bond_kernels.h"

namespace {

// ledger entries (`fixed_step.Ledger`)
enum { E0, WORK, DISSIPATED, POWER, DRIFT, MOVED, LEDGER_SIZE };

template <ffi::DataType DT>
struct StageInputs {
  const int32_t *i1, *i2, *slot;
  const ffi::NativeType<DT>*r0, *arms, *vref, *lig, *con, *im, *c, *qc, *qcd, *h;
  int64_t nb, n, nf, nc, m;
  ffi::NativeType<DT> l0;
  bool contact;
};

template <ffi::DataType DT>
ffi::Error ReadStages(Buf<ffi::S32> b1, Buf<ffi::S32> b2, Buf<DT> r0, Buf<ffi::S32> slot,
                      Buf<DT> q, Buf<DT> v, Buf<DT> f, Buf<DT> arms, Buf<DT> vref, Buf<DT> lig,
                      Buf<DT> con, Buf<DT> im, Buf<DT> c, Buf<DT> qc, Buf<DT> qcd, Buf<DT> h,
                      Buf<DT> led, double l0, int32_t contact, StageInputs<DT>* in) {
  const int64_t n = b1.element_count(), nf = q.element_count(), m = h.element_count();
  const int64_t ndof = slot.element_count();
  if (b2.element_count() != n || arms.element_count() != 4 * n ||
      vref.element_count() != 2 * n || r0.element_count() != 2 * n ||
      lig.element_count() != 3 * n || con.element_count() != 3 * n || ndof % 3 != 0 ||
      nf > ndof || v.element_count() != nf || f.element_count() != nf ||
      im.element_count() != nf || c.element_count() != nf || m < 1 ||
      qc.element_count() != m * (ndof - nf) || qcd.element_count() != qc.element_count() ||
      led.element_count() != LEDGER_SIZE) {
    return ffi::Error::InvalidArgument("verlet_stages: inconsistent array sizes");
  }
  *in = {b1.typed_data(), b2.typed_data(), slot.typed_data(), r0.typed_data(),
         arms.typed_data(), vref.typed_data(), lig.typed_data(), con.typed_data(),
         im.typed_data(), c.typed_data(), qc.typed_data(), qcd.typed_data(), h.typed_data(),
         ndof / 3, n, nf, ndof - nf, m, ffi::NativeType<DT>(l0), contact != 0};
  if (!BondsInRange(n, in->nb, in->i1, in->i2))
    return ffi::Error::InvalidArgument("verlet_stages: a bond's unit index is out of range");
  for (int64_t g = 0; g < ndof; ++g) {
    if (in->slot[g] < 0 || in->slot[g] >= ndof)
      return ffi::Error::InvalidArgument("verlet_stages: a DOF's slot is out of range");
  }
  return ffi::Error::Success();
}

// the global state x [3 nb] of the free state q [nf] and the prescribed values qc [nc]
template <class T>
void Assemble(int64_t ndof, int64_t nf, const int32_t* slot, const T* q, const T* qc, T* x) {
  for (int64_t g = 0; g < ndof; ++g) {
    const int64_t s = slot[g];
    x[g] = s < nf ? q[s] : qc[s - nf];
  }
}

// a stage's two half kicks (`fixed_step.integrate`'s Verlet step), one home for the forward
// call and the reverse's rebuilt stages: the first with damping explicit, v_half = v + h/2
// M^-1 (f - C v); the second implicit, v1 = (v_half + h/2 M^-1 f1) / (1 + h/2 M^-1 C)
template <class T>
INLINE T KickStart(T v, T f, T im, T c, T half) {
  return v + half * im * (f - c * v);
}
template <class T>
INLINE T KickEnd(T vh, T f1, T im, T c, T half) {
  return (vh + half * im * f1) / (T(1) + half * im * c);
}

// stage k's force on the free units f [nf] at q; returns the potential energy, and through
// `power` the power the prescribed velocities put in (their reactions times their velocities)
template <ffi::DataType DT>
ffi::NativeType<DT> StageForce(const StageInputs<DT>& in, int64_t k,
                               const ffi::NativeType<DT>* q, ffi::NativeType<DT>* f,
                               ffi::NativeType<DT>* power) {
  using T = ffi::NativeType<DT>;
  const int64_t ndof = 3 * in.nb, n = in.n, nf = in.nf;
  const T* qcd = in.qcd + k * in.nc;
  thread_local std::vector<T> x, grad;
  x.resize(ndof);
  grad.resize(ndof);
  Assemble(ndof, nf, in.slot, q, in.qc + k * in.nc, x.data());
  const T energy = BondForce(in.nb, n, in.i1, in.i2, x.data(), in.arms, in.vref, in.r0, in.lig,
                             in.con, in.l0, in.contact, grad.data());
  T p = T(0);
  for (int64_t d = 0; d < ndof; ++d) {
    const int64_t s = in.slot[d];
    if (s < nf) {
      f[s] = -grad[d];
    } else {
      p += grad[d] * qcd[s - nf];
    }
  }
  *power = p;
  return energy;
}

// the m stages from (q, v, f) -> (q1, v1), the ledger led -> led1 [LEDGER_SIZE] and the stage
// forces fs [m, nf] (the last the step's force)
template <ffi::DataType DT>
ffi::Error Stages(Buf<ffi::S32> b1, Buf<ffi::S32> b2, Buf<DT> r0, Buf<ffi::S32> slot, Buf<DT> q,
                  Buf<DT> v, Buf<DT> f, Buf<DT> arms, Buf<DT> vref, Buf<DT> lig, Buf<DT> con,
                  Buf<DT> im, Buf<DT> c, Buf<DT> qc, Buf<DT> qcd, Buf<DT> h, Buf<DT> led,
                  Res<DT> q1, Res<DT> v1, Res<DT> led1, Res<DT> fs, double l0, int32_t contact) {
  using T = ffi::NativeType<DT>;
  StageInputs<DT> in;
  if (auto err = ReadStages(b1, b2, r0, slot, q, v, f, arms, vref, lig, con, im, c, qc, qcd, h,
                            led, l0, contact, &in);
      err.failure())
    return err;
  const int64_t nf = in.nf;
  T *qo = q1->typed_data(), *vo = v1->typed_data(), *lo = led1->typed_data();
  T* fo = fs->typed_data();
  std::copy(q.typed_data(), q.typed_data() + nf, qo);
  std::copy(v.typed_data(), v.typed_data() + nf, vo);
  std::copy(led.typed_data(), led.typed_data() + LEDGER_SIZE, lo);
  thread_local std::vector<T> vh;
  vh.resize(nf);
  const T* fk = f.typed_data();
  for (int64_t k = 0; k < in.m; ++k) {
    const T hk = in.h[k], half = T(0.5) * hk;
    T diss = T(0);
    for (int64_t i = 0; i < nf; ++i) {
      diss += vo[i] * in.c[i] * vo[i];
      vh[i] = KickStart(vo[i], fk[i], in.im[i], in.c[i], half);
      qo[i] += hk * vh[i];
    }
    T* f1 = fo + k * nf;
    T power;
    const T energy = StageForce(in, k, qo, f1, &power);
    T kinetic = T(0), diss1 = T(0);
    for (int64_t i = 0; i < nf; ++i) {
      vo[i] = KickEnd(vh[i], f1[i], in.im[i], in.c[i], half);
      kinetic += vo[i] * (T(1) / in.im[i]) * vo[i];
      diss1 += vo[i] * in.c[i] * vo[i];
    }
    // the work-energy account (fixed_step.ledger_step)
    lo[WORK] += half * (lo[POWER] + power);
    lo[DISSIPATED] += half * (diss + diss1);
    const T change = T(0.5) * kinetic + energy - lo[E0];
    lo[DRIFT] = std::max(lo[DRIFT], std::fabs(change - lo[WORK] + lo[DISSIPATED]));
    lo[MOVED] = std::max(lo[MOVED], std::max(std::fabs(change), std::fabs(lo[WORK])));
    lo[POWER] = power;
    fk = f1;
  }
  return ffi::Error::Success();
}

// reverse of Stages: the cotangents qb1, vb1, fb1 [nf] of the step's q1, v1 and force (the
// ledger is not differentiated) -> the cotangents of q, v, f, arms, void_ref, the two material
// arrays, the inverse mass, the damping and qc. The stages are rebuilt from the forward's
// stage forces fs; each stage's force is reversed by the Hessian product at its end
template <ffi::DataType DT>
ffi::Error StagesVjp(Buf<ffi::S32> b1, Buf<ffi::S32> b2, Buf<DT> r0, Buf<ffi::S32> slot,
                     Buf<DT> q, Buf<DT> v, Buf<DT> f, Buf<DT> arms, Buf<DT> vref, Buf<DT> lig,
                     Buf<DT> con, Buf<DT> im, Buf<DT> c, Buf<DT> qc, Buf<DT> qcd, Buf<DT> h,
                     Buf<DT> led, Buf<DT> fs, Buf<DT> qb1, Buf<DT> vb1, Buf<DT> fb1, Res<DT> qb,
                     Res<DT> vb, Res<DT> fb, Res<DT> armsb, Res<DT> vrefb, Res<DT> ligb,
                     Res<DT> conb, Res<DT> imb, Res<DT> cb, Res<DT> qcb, double l0,
                     int32_t contact) {
  using T = ffi::NativeType<DT>;
  StageInputs<DT> in;
  if (auto err = ReadStages(b1, b2, r0, slot, q, v, f, arms, vref, lig, con, im, c, qc, qcd, h,
                            led, l0, contact, &in);
      err.failure())
    return err;
  const int64_t nf = in.nf, n = in.n, m = in.m, nc = in.nc, ndof = 3 * in.nb;
  if (fs.element_count() != m * nf || qb1.element_count() != nf ||
      vb1.element_count() != nf || fb1.element_count() != nf)
    return ffi::Error::InvalidArgument("verlet_stages_vjp: cotangent sizes do not match");
  const T *im_ = in.im, *c_ = in.c, *F = fs.typed_data();
  // the stages' start states qs, vs [m + 1, nf], rebuilt from the stage forces
  thread_local std::vector<T> qs, vs, x, gbar, qbar, ab, vrb, lb, cbk;
  qs.resize((m + 1) * nf);
  vs.resize((m + 1) * nf);
  std::copy(q.typed_data(), q.typed_data() + nf, qs.begin());
  std::copy(v.typed_data(), v.typed_data() + nf, vs.begin());
  for (int64_t k = 0; k < m; ++k) {
    const T hk = in.h[k], half = T(0.5) * hk;
    const T* fk = k ? F + (k - 1) * nf : f.typed_data();
    const T *f1 = F + k * nf, *qk = qs.data() + k * nf, *vk = vs.data() + k * nf;
    T *qn = qs.data() + (k + 1) * nf, *vn = vs.data() + (k + 1) * nf;
    #pragma GCC ivdep  // distinct arrays: vectorised without alias checks
    for (int64_t i = 0; i < nf; ++i) {
      const T vh = KickStart(vk[i], fk[i], im_[i], c_[i], half);
      qn[i] = qk[i] + hk * vh;
      vn[i] = KickEnd(vh, f1[i], im_[i], c_[i], half);
    }
  }
  T *qbo = qb->typed_data(), *vbo = vb->typed_data(), *fbo = fb->typed_data();
  T *ao = armsb->typed_data(), *vro = vrefb->typed_data(), *lo = ligb->typed_data();
  T *co = conb->typed_data(), *imo = imb->typed_data(), *cbo = cb->typed_data();
  T* qco = qcb->typed_data();
  std::copy(qb1.typed_data(), qb1.typed_data() + nf, qbo);
  std::copy(vb1.typed_data(), vb1.typed_data() + nf, vbo);
  std::copy(fb1.typed_data(), fb1.typed_data() + nf, fbo);
  std::fill(ao, ao + 4 * n, T(0));
  std::fill(vro, vro + 2 * n, T(0));
  std::fill(lo, lo + 3 * n, T(0));
  std::fill(co, co + 3 * n, T(0));
  std::fill(imo, imo + nf, T(0));
  std::fill(cbo, cbo + nf, T(0));
  x.resize(ndof);
  gbar.resize(ndof);
  qbar.resize(ndof);
  ab.resize(4 * n);
  vrb.resize(2 * n);
  lb.resize(3 * n);
  cbk.resize(3 * n);
  for (int64_t k = m - 1; k >= 0; --k) {
    const T hk = in.h[k], half = T(0.5) * hk;
    const T* fk = k ? F + (k - 1) * nf : f.typed_data();
    const T *f1 = F + k * nf, *qn = qs.data() + (k + 1) * nf, *vk = vs.data() + k * nf;
    const T* vn = vs.data() + (k + 1) * nf;
    // v1 = (vh + h/2 im f1) / den: fbo becomes f1's whole cotangent, vbo vh's
    #pragma GCC ivdep  // distinct arrays: vectorised without alias checks
    for (int64_t i = 0; i < nf; ++i) {
      const T den = T(1) + half * im_[i] * c_[i];  // KickEnd's denominator
      const T numb = vbo[i] / den, denb = -vbo[i] * vn[i] / den;
      fbo[i] += numb * half * im_[i];
      imo[i] += numb * half * f1[i] + denb * half * c_[i];
      cbo[i] += denb * half * im_[i];
      vbo[i] = numb;
    }
    // f1 = -dV/dq_f at the stage's end: the Hessian product with -fbo
    for (int64_t d = 0; d < ndof; ++d) {
      const int64_t s = in.slot[d];
      gbar[d] = s < nf ? -fbo[s] : T(0);
    }
    Assemble(ndof, nf, in.slot, qn, in.qc + k * nc, x.data());
    BondForceVjp(in.nb, n, in.i1, in.i2, x.data(), in.arms, in.vref, in.r0, in.lig, in.con,
                 in.l0, in.contact, T(0), gbar.data(), qbar.data(), ab.data(), vrb.data(),
                 lb.data(), cbk.data());
    for (int64_t j = 0; j < 4 * n; ++j) ao[j] += ab[j];
    for (int64_t j = 0; j < 2 * n; ++j) vro[j] += vrb[j];
    for (int64_t j = 0; j < 3 * n; ++j) {
      lo[j] += lb[j];
      co[j] += cbk[j];
    }
    for (int64_t d = 0; d < ndof; ++d) {
      const int64_t s = in.slot[d];
      if (s < nf) {
        qbo[s] += qbar[d];
      } else {
        qco[k * nc + s - nf] = qbar[d];
      }
    }
    // q1 = q + h vh and vh = v + h/2 im (f - c v)
    #pragma GCC ivdep  // distinct arrays: vectorised without alias checks
    for (int64_t i = 0; i < nf; ++i) {
      const T vhb = vbo[i] + hk * qbo[i];
      imo[i] += vhb * half * (fk[i] - c_[i] * vk[i]);
      cbo[i] -= vhb * half * im_[i] * vk[i];
      vbo[i] = vhb * (T(1) - half * im_[i] * c_[i]);
      fbo[i] = vhb * half * im_[i];
    }
  }
  return ffi::Error::Success();
}

}  // namespace

// the bindings: the lattice's constants (b1, b2, r0, slot), then the 13 inputs (q, v, f, arms,
// vref, lig, con, inverse mass, damping, qc, qcd, h, ledger)
#define ARG(T) .Arg<Buf<T>>()
#define RET(DT) .Ret<Buf<DT>>()
#define ARGS4(DT) ARG(DT) ARG(DT) ARG(DT) ARG(DT)
#define STAGES_ARGS(DT) \
  ffi::Ffi::Bind() ARG(ffi::S32) ARG(ffi::S32) ARG(DT) ARG(ffi::S32) ARGS4(DT) ARGS4(DT) ARGS4(DT) ARG(DT)
#define STAGE_ATTRS .Attr<double>("l0").Attr<int32_t>("contact")
// -> q1, v1, ledger1, stage forces
#define STAGES(DT) STAGES_ARGS(DT) RET(DT) RET(DT) RET(DT) RET(DT) STAGE_ATTRS
// with the stage forces and the cotangents of q1, v1, f1 -> the cotangents of the first 10 inputs
#define STAGES_VJP(DT)                                                                        \
  STAGES_ARGS(DT) ARGS4(DT) RET(DT) RET(DT) RET(DT) RET(DT) RET(DT) RET(DT) RET(DT) RET(DT)    \
      RET(DT) RET(DT) STAGE_ATTRS

XLA_FFI_DEFINE_HANDLER_SYMBOL(MetarigVerletStagesF64, Stages<ffi::F64>, STAGES(ffi::F64));
XLA_FFI_DEFINE_HANDLER_SYMBOL(MetarigVerletStagesF32, Stages<ffi::F32>, STAGES(ffi::F32));
XLA_FFI_DEFINE_HANDLER_SYMBOL(MetarigVerletStagesVjpF64, StagesVjp<ffi::F64>,
                              STAGES_VJP(ffi::F64));
XLA_FFI_DEFINE_HANDLER_SYMBOL(MetarigVerletStagesVjpF32, StagesVjp<ffi::F32>,
                              STAGES_VJP(ffi::F32));
