/*
 * bess-ded controller core (docs/firmware-spec.md sections 2, 4, 5, 6, 6.1).
 *
 * Bit-exact C99 port of firmware_py/controllers.py (fixed core): pure functions on a
 * state struct; no heap, no floating point, int32/int64 arithmetic only. The constants
 * arrive already quantised (KTS, HTS, TSQ in Q1.30, BAND in Q24, D in samples, the ft
 * exponent as p / 2^n): q24/q30 of binary64 config values (NUM-4, NUM-6) happen outside
 * the core.
 */
#ifndef BESSDED_CONTROLLER_H
#define BESSDED_CONTROLLER_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Controller kinds (CFG-3). The values are part of the binding's ABI. */
#define BD_KIND_PC 0
#define BD_KIND_PI 1
#define BD_KIND_RESET 2
#define BD_KIND_DWELL 3
#define BD_KIND_FT 4

/* The Q54 image of the int32 Q24 range (NUM-7): [-2^61, 2^61 - 2^30]. */
#define BD_STATE_MAX ((int64_t)INT32_MAX * ((int64_t)1 << 30))
#define BD_STATE_MIN ((int64_t)INT32_MIN * ((int64_t)1 << 30))

/* Errors of bd_ctrl_config_check. */
#define BD_OK 0
#define BD_ERR_KIND 1
#define BD_ERR_GAIN 2     /* KTS, HTS or TSQ negative (NUM-6: 0 <= q30 <= 2^31 - 1) */
#define BD_ERR_BAND 3     /* BAND negative */
#define BD_ERR_EXPONENT 4 /* ft: not a = p/2^n, p odd, 0 < p < 2^n, 1 <= n <= 4 */

/* The controller's constants (CTRL-1..3), integers only. */
typedef struct {
    int32_t kind;         /* BD_KIND_* */
    int32_t kts;          /* q30(k*ts) */
    int32_t hts;          /* q30(h*ts) */
    int32_t tsq;          /* q30(ts) */
    int32_t band;         /* q24(band) */
    uint32_t dwell;       /* D = ceil(dwell/ts - 1e-9) for dwell, else 0 (CTRL-2) */
    uint32_t pow_num;     /* ft: p (odd) */
    uint32_t pow_sqrts;   /* ft: n, a = p / 2^n */
} bd_ctrl_config;

/* The controller state (CTRL-4). The counters saturate at UINT32_MAX instead of
 * wrapping (firmware_py's are unbounded; since_reset is only compared with D). */
typedef struct {
    int64_t lam;          /* lambda, Q54 */
    int64_t nu;           /* nu, Q54 */
    int32_t xi_prev;      /* previous xi, Q24 */
    int32_t armed;        /* 0/1 */
    uint32_t since_reset;
    uint32_t resets;
    uint32_t saturations; /* ctrl_sats (STEP-9) */
} bd_ctrl_state;

/* What one step returns besides the new state. */
typedef struct {
    int64_t dlam;         /* the lambda increment applied, Q54 */
    int32_t reset;        /* 0/1: nu was reset at this sample */
} bd_step_out;

/* One row of bd_ctrl_run: the output and the state after the step. */
typedef struct {
    bd_ctrl_state state;
    bd_step_out out;
} bd_step_record;

/* Arithmetic helpers (NUM-2, NUM-5, NUM-7, NUM-8), exposed for tests. */
int64_t bd_shr_floor(int64_t x, unsigned n);           /* floor(x / 2^n), any sign */
int64_t bd_mulq(int64_t a, int64_t b);                 /* (a*b + 2^23) >> 24 */
int64_t bd_sat54(int64_t x, uint32_t *count);          /* clamp to Q54 range, count */
int32_t bd_sat32(int64_t x, uint32_t *count);          /* clamp to int32, count */
int32_t bd_wire(int64_t x);                            /* (x + 2^29) >> 30 */
uint64_t bd_isqrt_u64(uint64_t x);                     /* exact floor(sqrt(x)) */
int64_t bd_fpow(int32_t v, uint32_t pow_num, uint32_t pow_sqrts); /* |v|^(p/2^n), Q24 */

/* BD_OK, or the first BD_ERR_* the constants violate. */
int bd_ctrl_config_check(const bd_ctrl_config *cfg);

/* CTRL-4: the initial state for a Q24 lambda(0). */
void bd_ctrl_init(bd_ctrl_state *s, int32_t lambda0_q24);

/* The wire lambda of a state (NUM-8). */
int32_t bd_ctrl_wire_lambda(const bd_ctrl_state *s);

/* One controller step (section 6): *s is advanced in place; *out (may be NULL) gets
 * dlam and reset. cfg must pass bd_ctrl_config_check. */
void bd_ctrl_step(const bd_ctrl_config *cfg, bd_ctrl_state *s, int32_t xi,
                  bd_step_out *out);

/* n steps with xi[0..n-1]; rec[t] (may be NULL) gets the output and state after step t.
 * For replay and timing from a host. */
void bd_ctrl_run(const bd_ctrl_config *cfg, bd_ctrl_state *s, const int32_t *xi,
                 size_t n, bd_step_record *rec);

/* XI-2, XI-3: the consensus error from the own wire lambda, the pin (PIN, 0 if not
 * pinned or no price), the price rho, and n alive RUNNING neighbours (W_j, lambda_j).
 * Exact for n < 2^23 terms (each |mulq| < 2^40). A clamp adds 1 to *sat_count
 * (the runtime's sat_xi, not ctrl_sats). */
int32_t bd_xi(int32_t lam_wire, int32_t pin, int32_t rho, const int32_t *weights,
              const int32_t *lam_j, size_t n, uint32_t *sat_count);

/* WMSR-1, WMSR-2: the resilient update's trimming, in place before bd_xi: up to f of the
 * n terms (W_j, lambda_j) strictly above lam_wire and up to f strictly below are removed
 * (the furthest first; of equal lambda_j the largest W_j); returns the terms left, in
 * weights[0..] and lam_j[0..] (their order changed). f = 0 leaves all n. */
size_t bd_wmsr_trim(int32_t lam_wire, uint32_t f, int32_t *weights, int32_t *lam_j, size_t n);

#ifdef __cplusplus
}
#endif

#endif /* BESSDED_CONTROLLER_H */
