/* The snakeboard's closed-form RDP step (alpha = 1/2, exp retraction; docs/integrators.md) in C,
 * for scripts/bench.py: the compiled-code baseline that ldap_jax's closed-form kernel is timed
 * against. The arithmetic of Snakeboard.kernel_step in ldap_jax/systems/_snakeboard.py at
 * alpha = 1/2 (positions only, no diagnostics): the steering angle turned twice by one sincos of
 * d = h u_phi / 2 and renormalised, the momenta folded (pu_{k+1} = d_u l + h f_{k+1/2} / 2), one
 * sincos of the heading increment, so the trajectories agree to round-off (bench.py checks it).
 * Built at bench time with the system's C compiler (-O3 -march=native, no -ffast-math: it would
 * change the arithmetic); nothing here is part of the library.
 *
 * Written for speed as careful scalar C is: the constants of the model and the step (m l^2, 1/I,
 * 1/(2 J), h/2, ...) hoisted out of the loops, one sincos per angle (none of an angle the state
 * already holds), reciprocals instead of repeated divisions, the controls at t_k carried from the
 * previous step (one sin per term and step), the steps of one maneuver in the inner loop, the
 * state in registers. Two ways to get sin and cos:
 *   - libm: glibc's sincos and sin (correctly rounded in practice; a call each);
 *   - poly: the branch-free fdlibm kernels that ldap_jax's sincos uses (one argument reduction,
 *     two polynomials), inlined, so the compiler schedules them with the step.
 * (A variant with the batch as the inner loop, a block of maneuvers advanced one step at a time,
 * was slower here: gcc vectorised it only 2 wide, through gathers of the array of states.)
 *
 * Controls: channel c of maneuver b is sum_j A[b][c][j] sin(W[b][c][j] t + P[b][c][j]).
 * init[b] = (theta, x, y, psi, phi, pu0, pu1, mu0, mu1); ctl[b] = A (2 x nt), W, P.
 */
#include <math.h>
#include <stddef.h>
#ifdef _OPENMP
#include <omp.h>
#endif

/* Number of OpenMP threads for the rollouts below (1 without OpenMP). */
void set_threads(int n) {
#ifdef _OPENMP
  omp_set_num_threads(n);
#else
  (void)n;
#endif
}

/* ---------------------------------------------------------------- sin and cos */
/* fdlibm __kernel_sin / __kernel_cos on |r| <= pi/4 after a Cody-Waite reduction by pi/2 (the
 * coefficients and the 33-bit split of pi/2 of ldap_jax._numerics); branch-free. */
static inline void sincos_poly(double x, double *s_out, double *c_out) {
  const double S1 = -1.66666666666666324348e-01, S2 = 8.33333333332248946124e-03,
               S3 = -1.98412698298579493134e-04, S4 = 2.75573137070700676789e-06,
               S5 = -2.50507602534068634195e-08, S6 = 1.58969099521155010221e-10;
  const double C1 = 4.16666666666666019037e-02, C2 = -1.38888888888741095749e-03,
               C3 = 2.48015872894767294178e-05, C4 = -2.75573143513906633035e-07,
               C5 = 2.08757232129817482790e-09, C6 = -1.13596475577881948265e-11;
  const double P1 = 1.57079632673412561417e00, P2 = 6.07710050630396597660e-11,
               P3 = 2.02226624871116645580e-21, TWO_OVER_PI = 0.63661977236758134308;
  double n = nearbyint(x * TWO_OVER_PI);
  double r = ((x - n * P1) - n * P2) - n * P3;
  double z = r * r;
  double ps = S6;
  ps = ps * z + S5;
  ps = ps * z + S4;
  ps = ps * z + S3;
  ps = ps * z + S2;
  ps = ps * z + S1;
  double pc = C6;
  pc = pc * z + C5;
  pc = pc * z + C4;
  pc = pc * z + C3;
  pc = pc * z + C2;
  pc = pc * z + C1;
  double s = r + r * z * ps;
  double c = (1.0 - 0.5 * z) + z * z * pc;
  long q = (long)n & 3;
  double sin_ = (q & 1) ? c : s, cos_ = (q & 1) ? s : c;
  *s_out = (q >= 2) ? -sin_ : sin_;
  *c_out = (q == 1 || q == 2) ? -cos_ : cos_;
}

static inline double sin_poly(double x) {
  double s, c;
  sincos_poly(x, &s, &c);
  return s;
}

static inline void sincos_libm(double x, double *s, double *c) {
  *s = sin(x);
  *c = cos(x); /* gcc merges the pair into one sincos call at -O3 */
}

/* ---------------------------------------------------------------- the step */
typedef struct { /* the model and the step size, hoisted */
  double h, half_h, ml2, I, inv_I, two_J, inv_2J, m, two_l, eps4;
} consts_t;

static inline consts_t make_consts(double h, double m, double l, double I, double J) {
  consts_t k = {h, 0.5 * h, m * l * l, I, 1.0 / I, 2 * J, 1.0 / (2 * J), m, 2 * l, 1.220703125e-4};
  return k;
}

typedef struct {
  double c, s, x, y, th, psi, phi, cphi, sphi, pu0, pu1, mu0, mu1, f0, f1;
} state_t;

/* One RDP step with the controls (g0, g1) at t_{k+1}; SINCOS is sincos_libm or sincos_poly. */
#define DEFINE_STEP(NAME, SINCOS)                                                                \
  static inline void NAME(state_t *st, double g0, double g1, const consts_t *k) {               \
    double fa0 = 0.5 * (st->f0 + g0), fa1 = 0.5 * (st->f1 + g1);                                \
    double b0 = st->pu0 + k->half_h * fa0, b1 = st->pu1 + k->half_h * fa1;                       \
    double uphi = b1 * k->inv_2J;                                                                \
    double sd, cd;                                                                               \
    SINCOS(k->half_h * uphi, &sd, &cd);                                                          \
    double ck = st->cphi, sk = st->sphi;                                                         \
    double sa = sk * cd + ck * sd, ca = ck * cd - sk * sd;                                       \
    double sn = sa * cd + ca * sd, cn = ca * cd - sa * sd;                                       \
    double unit = 1.5 - 0.5 * (sn * sn + cn * cn);                                               \
    sn *= unit;                                                                                  \
    cn *= unit;                                                                                  \
    double s2a = 2 * sa * ca, s2k = 2 * sk * ck;                                                 \
    double kappa = 4 * ca * ck * (ca * ck + sa * sk);                                            \
    double nu = st->mu0 * s2k - st->mu1 * k->two_l * ck * ck;                                    \
    double bp = b0 * k->inv_I;                                                                   \
    double inv_det = 1.0 / (k->ml2 * kappa - k->I * s2k * s2a);                                  \
    double upsi = (k->ml2 * kappa * bp - s2a * nu) * inv_det;                                    \
    double cc = (nu - k->I * s2k * bp) * inv_det;                                                \
    double xi0 = cc * s2a, xi1 = -k->two_l * ca * ca * cc;                                       \
    st->pu0 = k->I * (upsi + xi0) + k->half_h * fa0;                                             \
    st->pu1 = k->two_J * uphi + k->half_h * fa1;                                                 \
    st->mu0 = k->ml2 * xi0 + k->I * upsi;                                                        \
    st->mu1 = k->m * xi1;                                                                        \
    double w = k->h * xi0, v2 = k->h * xi1;                                                      \
    int small = fabs(w) < k->eps4;                                                               \
    double ws = small ? 1.0 : w, sw, cw;                                                         \
    SINCOS(ws, &sw, &cw);                                                                        \
    double inv_ws = 1.0 / ws, w2 = w * w;                                                        \
    double A = small ? 1 - w2 / 6 + w2 * w2 / 120 : sw * inv_ws;                                 \
    double B = small ? w / 2 - w * w2 / 24 + w * w2 * w2 / 720 : (1 - cw) * inv_ws;             \
    if (small) {                                                                                 \
      cw = 1 - w2 / 2 + w2 * w2 / 24;                                                            \
      sw = w - w * w2 / 6 + w * w2 * w2 / 120;                                                   \
    }                                                                                            \
    double dx = A * v2, dy = B * v2, c = st->c, s = st->s;                                       \
    st->x += c * dx - s * dy;                                                                    \
    st->y += s * dx + c * dy;                                                                    \
    st->th += w;                                                                                 \
    st->c = c * cw - s * sw;                                                                     \
    st->s = s * cw + c * sw;                                                                     \
    st->psi += k->h * upsi;                                                                      \
    st->phi += k->h * uphi;                                                                      \
    st->cphi = cn;                                                                               \
    st->sphi = sn;                                                                               \
    st->f0 = g0;                                                                                 \
    st->f1 = g1;                                                                                 \
  }

DEFINE_STEP(step_libm, sincos_libm)
DEFINE_STEP(step_poly, sincos_poly)

static inline double control_libm(const double *A, const double *W, const double *P, int nt, double t) {
  double v = 0.0;
  for (int j = 0; j < nt; j++) v += A[j] * sin(W[j] * t + P[j]);
  return v;
}

static inline double control_poly(const double *A, const double *W, const double *P, int nt, double t) {
  double v = 0.0;
  for (int j = 0; j < nt; j++) v += A[j] * sin_poly(W[j] * t + P[j]);
  return v;
}

static inline state_t initial_state(const double *in, const double *A, const double *W, const double *P,
                                    int nt) {
  state_t st = {cos(in[0]), sin(in[0]), in[1], in[2], in[0], in[3], in[4], cos(in[4]), sin(in[4]),
                in[5], in[6], in[7], in[8], control_libm(A, W, P, nt, 0.0),
                control_libm(A + nt, W + nt, P + nt, nt, 0.0)};
  return st;
}

static inline void store(double *o, const state_t *st) {
  o[0] = st->x, o[1] = st->y, o[2] = st->th, o[3] = st->psi, o[4] = st->phi;
}

/* A scalar loop over the steps of each maneuver (maneuvers split over the OpenMP threads). With
 * ALL the nodes are stored (q: (B, N+1, 5), for the agreement check), else the final one
 * (q: (B, 5)), as a positions-only rollout (save="final") returns. */
#define DEFINE_ROLLOUT(NAME, STEP, CONTROL, ALL)                                                   \
  void NAME(int B, int N, int nt, double h, double m, double l, double I, double J, const double *init, \
            const double *ctl, double *q) {                                                         \
    const consts_t k = make_consts(h, m, l, I, J);                                                  \
    _Pragma("omp parallel for schedule(static)") for (int b = 0; b < B; b++) {                      \
      const double *A = ctl + (size_t)6 * nt * b, *W = A + 2 * nt, *P = A + 4 * nt;                 \
      state_t st = initial_state(init + 9 * b, A, W, P, nt);                                        \
      double *o = q + (size_t)5 * (ALL ? N + 1 : 1) * b;                                            \
      for (int i = 0; i < N; i++) {                                                                 \
        if (ALL) store(o + 5 * i, &st);                                                             \
        double t1 = (i + 1) * h;                                                                    \
        STEP(&st, CONTROL(A, W, P, nt, t1), CONTROL(A + nt, W + nt, P + nt, nt, t1), &k);           \
      }                                                                                             \
      store(o + (ALL ? 5 * N : 0), &st);                                                            \
    }                                                                                               \
  }

DEFINE_ROLLOUT(rollout_libm, step_libm, control_libm, 1)
DEFINE_ROLLOUT(rollout_final_libm, step_libm, control_libm, 0)
DEFINE_ROLLOUT(rollout_poly, step_poly, control_poly, 1)
DEFINE_ROLLOUT(rollout_final_poly, step_poly, control_poly, 0)
