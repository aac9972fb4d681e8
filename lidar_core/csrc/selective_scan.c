/* Fused CPU selective scan (Mamba's S6 recurrence), forward and backward.
 *
 * The same maths as model_export/scan.py's selective_scan_ref, one (batch, channel) row at a
 * time, with the state kept in registers/L1 instead of (B, E, L, N) tensors. Compiled twice
 * from this file: REAL=float (training and inference) and REAL=double (gradcheck).
 *
 * Layouts, all C-contiguous:
 *   u, delta, y, du, ddelta: (B, E, L)
 *   A: (E, N)                 Bm, Cm, dB, dC: (B, L, N)      D: (E,)
 *   dA: (B, E, N)  per-batch partial sums (summed over the batch by the caller)
 * Each call handles batch rows [b0, b1), so the caller can split a batch across threads:
 * rows never share an output element (dB/dC are per batch row, accumulated over channels).
 * The forward also comes over flat (batch, channel) rows [r0, r1) (scan_fwd_rows), which
 * inference uses: at B = 1 the batch alone cannot be split across threads.
 *
 * Recurrence, for t = 0 … L−1, with a_t = exp(Δ_t A) and b_t = Δ_t u_t B_t:
 *   h_t = a_t ⊙ h_{t−1} + b_t,   h_{−1} = s,   y_t = C_t · h_t + D u_t
 * Open scan: s = 0. Circular scan: s = z / (1 − P), where z is h_{L−1} of the run from 0 and
 * P = Π_t a_t (elementwise), so that h_{L−1} = s: the ring's periodic state. 1 − P is clamped
 * at 1e−6 like the reference; where the clamp holds, s does not depend on P.
 *
 * Backward (adjoint g_t = ∂loss/∂h_t):  g_t = C_t dy_t + a_{t+1} g_{t+1};  μ = ∂loss/∂s = a_0 g_0.
 * Circular: s = z/(1−P) sends ν = μ/(1−P) into z (the output-free run from 0, whose adjoint
 * is g'_t = ν Π_{k>t} a_k) and ν·s·P into every ∂/∂(Δ_t A). With G = g + g' (the plain
 * adjoint recurrence, seeded with ν at the last step) and h_{t−1} = h0_{t−1} + Π_{k<t} a_k · s,
 * the terms collapse to
 *   ∂/∂(Δ_t A) = a_t G_t h_{t−1} − [clamped] ν P s,      ∂/∂b_t = G_t,
 * so the backward needs neither the run from 0's states nor a second adjoint: one pass for
 * μ, one for everything else.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#ifdef SCAN_DOUBLE
#define REAL double
#define FN(name) name##_d
#define EXP exp
#define EXPM1 expm1
#else
#define REAL float
#define FN(name) name##_f
#define EXP expf
#define EXPM1 expm1f
#endif

#define RING_EPS ((REAL)1e-6)

/* a[t, n] = exp(Δ_t A_n) for every step, and the start state s (N,): the ring's periodic
 * state when circular, else 0. logp returns Σ_t Δ_t A (N,). */
static void decays_and_start(const REAL *restrict u, const REAL *restrict delta,
                             const REAL *restrict Bt, const REAL *restrict A, REAL *restrict a,
                             REAL *restrict s, REAL *restrict logp, int L, int N, int circular) {
    memset(s, 0, sizeof(REAL) * N);
    memset(logp, 0, sizeof(REAL) * N);
    for (int t = 0; t < L; t++) {
        const REAL dt = delta[t], dtu = delta[t] * u[t];
        REAL *restrict at = a + (size_t)t * N;
        const REAL *restrict bt = Bt + (size_t)t * N;
        for (int n = 0; n < N; n++) {
            at[n] = EXP(dt * A[n]);
            s[n] = at[n] * s[n] + dtu * bt[n]; /* the run from 0: z = its last state */
            logp[n] += dt * A[n];
        }
    }
    for (int n = 0; n < N; n++) {
        const REAL one_minus_p = -EXPM1(logp[n]);
        s[n] = circular ? s[n] / (one_minus_p > RING_EPS ? one_minus_p : RING_EPS) : 0;
    }
}

/* Forward over flat rows r = b·E + e in [r0, r1): any split of the B·E rows across threads,
 * so one scan at B = 1 (a few batch rows, hundreds of channels) still uses every thread. */
void FN(scan_fwd_rows)(const REAL *u, const REAL *delta, const REAL *A, const REAL *Bm,
                       const REAL *Cm, const REAL *D, REAL *y, int B, int E, int L, int N,
                       int circular, long r0, long r1) {
    (void)B;
    REAL *a = malloc(sizeof(REAL) * (size_t)L * N);
    REAL *v = malloc(sizeof(REAL) * 2 * (size_t)N);
    REAL *restrict h = v, *restrict logp = v + N;
    for (long r = r0; r < r1; r++) {
        const long b = r / E, e = r % E;
        const REAL *Bb = Bm + (size_t)b * L * N, *Cb = Cm + (size_t)b * L * N;
        const size_t row = (size_t)r * L;
        const REAL *ur = u + row, *dr = delta + row, *Ae = A + (size_t)e * N;
        REAL *yr = y + row;
        decays_and_start(ur, dr, Bb, Ae, a, h, logp, L, N, circular);
        const REAL De = D[e];
        for (int t = 0; t < L; t++) {
            const REAL du = dr[t] * ur[t];
            const REAL *restrict at = a + (size_t)t * N;
            const REAL *restrict bt = Bb + (size_t)t * N;
            const REAL *restrict ct = Cb + (size_t)t * N;
            REAL acc = 0;
            for (int n = 0; n < N; n++) {
                h[n] = at[n] * h[n] + du * bt[n];
                acc += ct[n] * h[n];
            }
            yr[t] = acc + De * ur[t];
        }
    }
    free(a);
    free(v);
}

/* Forward over batch rows [b0, b1) (the training path splits a batch by rows). */
void FN(scan_fwd)(const REAL *u, const REAL *delta, const REAL *A, const REAL *Bm, const REAL *Cm,
                  const REAL *D, REAL *y, int B, int E, int L, int N, int circular, int b0,
                  int b1) {
    FN(scan_fwd_rows)(u, delta, A, Bm, Cm, D, y, B, E, L, N, circular, (long)b0 * E,
                      (long)b1 * E);
}

void FN(scan_bwd)(const REAL *u, const REAL *delta, const REAL *A, const REAL *Bm, const REAL *Cm,
                  const REAL *D, const REAL *dy, REAL *du, REAL *ddelta, REAL *dA, REAL *dB,
                  REAL *dC, int B, int E, int L, int N, int circular, int b0, int b1) {
    const size_t LN = (size_t)L * N;
    REAL *a = malloc(sizeof(REAL) * LN);  /* decays a_t */
    REAL *hs = malloc(sizeof(REAL) * LN); /* states h_t of the scan from s */
    REAL *v = malloc(sizeof(REAL) * 6 * (size_t)N);
    REAL *restrict s = v, *restrict logp = v + N, *restrict G = v + 2 * N,
         *restrict corr = v + 3 * N, *restrict dAe = v + 4 * N, *restrict dla = v + 5 * N;
    for (int b = b0; b < b1; b++) {
        const REAL *Bb = Bm + (size_t)b * LN, *Cb = Cm + (size_t)b * LN;
        REAL *dBb = dB + (size_t)b * LN, *dCb = dC + (size_t)b * LN;
        memset(dBb, 0, sizeof(REAL) * LN);
        memset(dCb, 0, sizeof(REAL) * LN);
        for (int e = 0; e < E; e++) {
            const size_t row = ((size_t)b * E + e) * L;
            const REAL *ur = u + row, *dr = delta + row, *dyr = dy + row, *Ae = A + (size_t)e * N;
            REAL *dur = du + row, *ddr = ddelta + row;
            decays_and_start(ur, dr, Bb, Ae, a, s, logp, L, N, circular);
            for (int t = 0; t < L; t++) { /* states of the scan from s */
                const REAL dtu = dr[t] * ur[t];
                const REAL *restrict at = a + (size_t)t * N, *restrict bt = Bb + (size_t)t * N;
                const REAL *restrict prev = t ? hs + (size_t)(t - 1) * N : s;
                REAL *restrict cur = hs + (size_t)t * N;
                for (int n = 0; n < N; n++) cur[n] = at[n] * prev[n] + dtu * bt[n];
            }
            memset(G, 0, sizeof(REAL) * N);
            memset(corr, 0, sizeof(REAL) * N);
            if (circular) { /* μ = ∂loss/∂s first: ν = μ/(1−P) seeds G at the last step */
                for (int t = L - 1; t >= 0; t--) {
                    const REAL *restrict at = a + (size_t)t * N, *restrict ct = Cb + (size_t)t * N;
                    for (int n = 0; n < N; n++) G[n] = at[n] * (G[n] + ct[n] * dyr[t]);
                }
                for (int n = 0; n < N; n++) {
                    const REAL one_minus_p = -EXPM1(logp[n]);
                    const int clamped = !(one_minus_p > RING_EPS);
                    G[n] = G[n] / (clamped ? RING_EPS : one_minus_p); /* ν */
                    corr[n] = clamped ? G[n] * EXP(logp[n]) * s[n] : 0;
                }
            }
            memset(dAe, 0, sizeof(REAL) * N);
            const REAL De = D[e];
            for (int t = L - 1; t >= 0; t--) {
                const REAL *restrict at = a + (size_t)t * N, *restrict bt = Bb + (size_t)t * N;
                const REAL *restrict ct = Cb + (size_t)t * N, *restrict ht = hs + (size_t)t * N;
                const REAL *restrict hprev = t ? hs + (size_t)(t - 1) * N : s;
                REAL *restrict dbt = dBb + (size_t)t * N, *restrict dct = dCb + (size_t)t * N;
                const REAL dyt = dyr[t], dt = dr[t], ut = ur[t];
                REAL sum_dla_a = 0, sum_g_b = 0;
                for (int n = 0; n < N; n++) {
                    G[n] += ct[n] * dyt; /* G_t = C_t dy_t + a_{t+1} G_{t+1} */
                    dct[n] += dyt * ht[n];
                    dla[n] = at[n] * G[n] * hprev[n] - corr[n];
                    sum_dla_a += dla[n] * Ae[n];
                    sum_g_b += G[n] * bt[n];
                    dAe[n] += dla[n] * dt;
                    dbt[n] += G[n] * dt * ut;
                    G[n] *= at[n]; /* carry to t − 1 */
                }
                ddr[t] = sum_dla_a + ut * sum_g_b;
                dur[t] = dt * sum_g_b + De * dyt;
            }
            memcpy(dA + ((size_t)b * E + e) * N, dAe, sizeof(REAL) * N);
        }
    }
    free(a);
    free(hs);
    free(v);
}
