/* The snakeboard's closed-form RDP step (alpha = 1/2, exp retraction; DESIGN.md section 6) in C,
 * for scripts/bench.py: the compiled-code baseline that ldap_jax's fast path is timed against.
 * Same arithmetic as ldap_jax/integrators/_fast.py (positions only, no diagnostics), so the
 * trajectories agree to round-off (bench.py checks it). Built at bench time with the system's C
 * compiler; nothing here is part of the library.
 *
 * State per trajectory (SoA, length B each): th, x, y, psi, phi, pu0, pu1, mu0, mu1, up0, up1;
 * controls: channel c of trajectory b is sum_j A[b][c][j] sin(W[b][c][j] t + P[b][c][j]).
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

/* init[b] = (th, x, y, psi, phi, pu0, pu1, mu0, mu1); ctl[b] = A (2 x nt), W, P; q: (B, N+1, 5) */
void rollout(int B, int N, int nt, double h, double m, double l, double I, double J,
             const double *init, const double *ctl, double *q) {
#pragma omp parallel for schedule(static)
  for (int b = 0; b < B; b++) {
    const double *in = init + 9 * b, *A = ctl + (size_t)6 * nt * b, *W = A + 2 * nt, *P = A + 4 * nt;
    state_t st = {in[0], cos(in[0]), sin(in[0]), in[1], in[2], in[3], in[4], cos(in[4]), sin(in[4]),
                  in[5], in[6], in[7], in[8], 0.0, 0.0,
                  control(A, W, P, nt, 0.0), control(A + nt, W + nt, P + nt, nt, 0.0)};
    double *o = q + (size_t)5 * (N + 1) * b;
    for (int k = 0; k <= N; k++) {
      o[5 * k] = st.x, o[5 * k + 1] = st.y, o[5 * k + 2] = st.th, o[5 * k + 3] = st.psi, o[5 * k + 4] = st.phi;
      if (k == N) break;
      double t1 = (k + 1) * h;
      step(&st, control(A, W, P, nt, t1), control(A + nt, W + nt, P + nt, nt, t1), h, m, l, I, J);
    }
  }
}

/* The same rollout with the batch as the inner loop over structure-of-arrays state, so that the
 * compiler vectorises across trajectories (with -ffast-math, gcc calls glibc's vector sin/cos).
 * ctl as above; up to 4 sinusoid terms per channel. */
#define NTMAX 4
void rollout_simd(int B, int N, int nt, double h, double m, double l, double I, double J,
                  const double *init, const double *ctl, double *q) {
#pragma omp parallel
  {
    double th[64], x[64], y[64], psi[64], phi[64], cth[64], sth[64], cph[64], sph[64];
    double pu0[64], pu1[64], mu0[64], mu1[64], fp0[64], fp1[64], c0[64], c1[64];
    double A[2][NTMAX][64], W[2][NTMAX][64], P[2][NTMAX][64];
    const double a = 0.5, ml2 = m * l * l;
#pragma omp for schedule(static)
    for (int b0 = 0; b0 < B; b0 += 64) {
      int nb = B - b0 < 64 ? B - b0 : 64;
      for (int i = 0; i < nb; i++) {
        const double *in = init + 9 * (b0 + i), *cp = ctl + (size_t)6 * nt * (b0 + i);
        th[i] = in[0], x[i] = in[1], y[i] = in[2], psi[i] = in[3], phi[i] = in[4];
        cth[i] = cos(in[0]), sth[i] = sin(in[0]), cph[i] = cos(in[4]), sph[i] = sin(in[4]);
        pu0[i] = in[5], pu1[i] = in[6], mu0[i] = in[7], mu1[i] = in[8], fp0[i] = fp1[i] = 0.0;
        for (int ch = 0; ch < 2; ch++)
          for (int j = 0; j < NTMAX; j++) {
            int ok = j < nt;
            A[ch][j][i] = ok ? cp[ch * nt + j] : 0.0;
            W[ch][j][i] = ok ? cp[2 * nt + ch * nt + j] : 0.0;
            P[ch][j][i] = ok ? cp[4 * nt + ch * nt + j] : 0.0;
          }
        c0[i] = control(cp, cp + 2 * nt, cp + 4 * nt, nt, 0.0);
        c1[i] = control(cp + nt, cp + 3 * nt, cp + 5 * nt, nt, 0.0);
      }
      for (int k = 0; k <= N; k++) {
        for (int i = 0; i < nb; i++) {
          double *o = q + (size_t)5 * ((size_t)(N + 1) * (b0 + i) + k);
          o[0] = x[i], o[1] = y[i], o[2] = th[i], o[3] = psi[i], o[4] = phi[i];
        }
        if (k == N) break;
        double t1 = (k + 1) * h;
#pragma omp simd
        for (int i = 0; i < nb; i++) {
          double c10 = 0.0, c11 = 0.0;
          for (int j = 0; j < nt; j++) {
            c10 += A[0][j][i] * sin(W[0][j][i] * t1 + P[0][j][i]);
            c11 += A[1][j][i] * sin(W[1][j][i] * t1 + P[1][j][i]);
          }
          double fa0 = (1 - a) * c0[i] + a * c10, fa1 = (1 - a) * c1[i] + a * c11;
          double b_0 = pu0[i] + h * (a * fp0[i] + (1 - a) * fa0);
          double b_1 = pu1[i] + h * (a * fp1[i] + (1 - a) * fa1);
          double uphi = b_1 / (2 * J);
          double phia = phi[i] + a * h * uphi, phin = phi[i] + h * uphi;
          double sa = sin(phia), ca = cos(phia), sn = sin(phin), cn = cos(phin);
          double cp = cph[i], sp = sph[i];
          double s2a = 2 * sa * ca, s2k = 2 * sp * cp;
          double kappa = 4 * ca * cp * (ca * cp + sa * sp);
          double bb1 = b_0 / I, bb2 = mu0[i] * s2k - mu1[i] * 2 * l * cp * cp;
          double det = ml2 * kappa - I * s2k * s2a;
          double upsi = (ml2 * kappa * bb1 - s2a * bb2) / det;
          double cc = (bb2 - I * s2k * bb1) / det;
          double xi0 = cc * s2a, xi1 = -2 * l * ca * ca * cc;
          pu0[i] = I * (upsi + xi0), pu1[i] = 2 * J * uphi;
          mu0[i] = ml2 * xi0 + I * upsi, mu1[i] = m * xi1;
          double w = h * xi0, v2 = h * xi1;
          double small = fabs(w) < 1.220703125e-4, ws = small ? 1.0 : w;
          double sw = sin(ws), cw = cos(ws);
          double A_ = small ? 1 - w * w / 6 + w * w * w * w / 120 : sw / ws;
          double B_ = small ? w / 2 - w * w * w / 24 + w * w * w * w * w / 720 : (1 - cw) / ws;
          cw = small ? 1 - w * w / 2 + w * w * w * w / 24 : cw;
          sw = small ? w * A_ : sw;
          double dx = A_ * v2, dy = B_ * v2, c = cth[i], s = sth[i];
          x[i] += c * dx - s * dy, y[i] += s * dx + c * dy;
          cth[i] = c * cw - s * sw, sth[i] = s * cw + c * sw, th[i] += w;
          psi[i] += h * upsi, phi[i] = phin, cph[i] = cn, sph[i] = sn;
          fp0[i] = fa0, fp1[i] = fa1, c0[i] = c10, c1[i] = c11;
        }
      }
    }
  }
}
