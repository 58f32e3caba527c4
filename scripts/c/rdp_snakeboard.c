/* The snakeboard's closed-form RDP step (alpha = 1/2, exp retraction; docs/integrators.md) in C,
 * for scripts/bench.py: the compiled-code baseline that ldap_jax's closed-form kernel is timed
 * against. Same arithmetic as Snakeboard.kernel_step in ldap_jax/systems/_snakeboard.py (positions
 * only, no diagnostics; the previous step's force kept apart, which equals the library's folded
 * momentum at a constant step), so the trajectories agree to round-off (bench.py checks it). Built
 * at bench time with the system's C compiler; nothing here is part of the library.
 *
 * State per trajectory: the pose (theta, cos, sin, x, y), psi, phi with its cos and sin, the
 * incoming momenta pu (2) and mu (the 2 components that pair with e_1), the previous force and the
 * control values at t_k; controls: channel c of trajectory b is
 * sum_j A[b][c][j] sin(W[b][c][j] t + P[b][c][j]).
 * Output q[b][k][0..4] = (x, y, theta, psi, phi) at t_k = k h, k = 0..N.
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

typedef struct {
  double th, c, s, x, y, psi, phi, cphi, sphi, pu0, pu1, mu0, mu1, fp0, fp1, c0, c1;
} state_t;

static inline double control(const double *A, const double *W, const double *P, int nt, double t) {
  double v = 0.0;
  for (int j = 0; j < nt; j++) v += A[j] * sin(W[j] * t + P[j]);
  return v;
}

static inline void step(state_t *st, double c10, double c11, double h, double m, double l,
                        double I, double J) {
  const double a = 0.5, ml2 = m * l * l;
  double fa0 = (1 - a) * st->c0 + a * c10, fa1 = (1 - a) * st->c1 + a * c11;
  double b0 = st->pu0 + h * (a * st->fp0 + (1 - a) * fa0);
  double b1 = st->pu1 + h * (a * st->fp1 + (1 - a) * fa1);
  double uphi = b1 / (2 * J);
  double phia = st->phi + a * h * uphi, phin = st->phi + h * uphi;
  double sa = sin(phia), ca = cos(phia), sn = sin(phin), cn = cos(phin);
  double cp = st->cphi, sp = st->sphi;
  double s2a = 2 * sa * ca, s2k = 2 * sp * cp;
  double e10 = s2k, e11 = -2 * l * cp * cp;
  double kappa = 4 * ca * cp * (ca * cp + sa * sp);
  double bb1 = b0 / I, bb2 = st->mu0 * e10 + st->mu1 * e11;
  double det = ml2 * kappa - I * s2k * s2a;
  double upsi = (ml2 * kappa * bb1 - s2a * bb2) / det;
  double cc = (bb2 - I * s2k * bb1) / det;
  double xi0 = cc * s2a, xi1 = -2 * l * ca * ca * cc;
  st->pu0 = I * (upsi + xi0);
  st->pu1 = 2 * J * uphi;
  /* mu_{k+1} = (I + ad_{h xi}/2)^T mu_k; only the two components that pair with e_1 are kept */
  st->mu0 = ml2 * xi0 + I * upsi;
  st->mu1 = m * xi1;
  double w = h * xi0, v2 = h * xi1;
  double sw = sin(w), cw = cos(w), A_, B_;
  if (fabs(w) < 1.220703125e-4) { /* eps^(1/4), as the JAX kernel */
    A_ = 1 - w * w / 6 + w * w * w * w / 120;
    B_ = w / 2 - w * w * w / 24 + w * w * w * w * w / 720;
    cw = 1 - w * w / 2 + w * w * w * w / 24;
    sw = w * A_;
  } else {
    A_ = sw / w;
    B_ = (1 - cw) / w;
  }
  double dx = A_ * v2, dy = B_ * v2;
  st->x += st->c * dx - st->s * dy;
  st->y += st->s * dx + st->c * dy;
  double c = st->c * cw - st->s * sw, s = st->s * cw + st->c * sw;
  st->c = c;
  st->s = s;
  st->th += w;
  st->psi += h * upsi;
  st->phi = phin;
  st->cphi = cn;
  st->sphi = sn;
  st->fp0 = fa0;
  st->fp1 = fa1;
  st->c0 = c10;
  st->c1 = c11;
}

static inline state_t initial_state(const double *in, const double *A, const double *W, const double *P,
                                    int nt) {
  state_t st = {in[0], cos(in[0]), sin(in[0]), in[1], in[2], in[3], in[4], cos(in[4]), sin(in[4]),
                in[5], in[6], in[7], in[8], 0.0, 0.0,
                control(A, W, P, nt, 0.0), control(A + nt, W + nt, P + nt, nt, 0.0)};
  return st;
}

static inline void store(double *o, const state_t *st) {
  o[0] = st->x, o[1] = st->y, o[2] = st->th, o[3] = st->psi, o[4] = st->phi;
}

/* init[b] = (th, x, y, psi, phi, pu0, pu1, mu0, mu1); ctl[b] = A (2 x nt), W, P; q: (B, N+1, 5).
 * A scalar loop over the steps of each trajectory, trajectories split over the OpenMP threads. */
void rollout(int B, int N, int nt, double h, double m, double l, double I, double J,
             const double *init, const double *ctl, double *q) {
#pragma omp parallel for schedule(static)
  for (int b = 0; b < B; b++) {
    const double *A = ctl + (size_t)6 * nt * b, *W = A + 2 * nt, *P = A + 4 * nt;
    state_t st = initial_state(init + 9 * b, A, W, P, nt);
    double *o = q + (size_t)5 * (N + 1) * b;
    for (int k = 0; k <= N; k++) {
      store(o + 5 * k, &st);
      if (k == N) break;
      double t1 = (k + 1) * h;
      step(&st, control(A, W, P, nt, t1), control(A + nt, W + nt, P + nt, nt, t1), h, m, l, I, J);
    }
  }
}

/* The same rollout with the batch as the inner loop (blocks of 64 trajectories advanced one step
 * at a time), so that the compiler can vectorise the step across trajectories (with -ffast-math
 * gcc calls glibc's vector sin/cos). */
#define BLOCK 64
void rollout_simd(int B, int N, int nt, double h, double m, double l, double I, double J,
                  const double *init, const double *ctl, double *q) {
#pragma omp parallel for schedule(static)
  for (int b0 = 0; b0 < B; b0 += BLOCK) {
    int nb = B - b0 < BLOCK ? B - b0 : BLOCK;
    state_t st[BLOCK];
    for (int i = 0; i < nb; i++) {
      const double *A = ctl + (size_t)6 * nt * (b0 + i);
      st[i] = initial_state(init + 9 * (b0 + i), A, A + 2 * nt, A + 4 * nt, nt);
    }
    for (int k = 0; k <= N; k++) {
      for (int i = 0; i < nb; i++) store(q + 5 * ((size_t)(N + 1) * (b0 + i) + k), &st[i]);
      if (k == N) break;
      double t1 = (k + 1) * h;
#pragma omp simd
      for (int i = 0; i < nb; i++) {
        const double *A = ctl + (size_t)6 * nt * (b0 + i), *W = A + 2 * nt, *P = A + 4 * nt;
        step(&st[i], control(A, W, P, nt, t1), control(A + nt, W + nt, P + nt, nt, t1), h, m, l, I, J);
      }
    }
  }
}
