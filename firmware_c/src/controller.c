/*
 * bess-ded controller core: docs/firmware-spec.md sections 2, 4, 5, 6, 6.1, bit for bit
 * with firmware_py/controllers.py (fixed core). C99, no heap, no floating point.
 *
 * Portability: C99 leaves >> of a negative signed value implementation-defined and <<
 * of one undefined, so every shift of a signed quantity goes through bd_shr_floor
 * (floor division by 2^n from a non-negative shift) or a multiplication by 2^n.
 */
#include "bessded/controller.h"

#define Q 24u                      /* fractional bits of a word (NUM-1) */
#define GUARD 30u                  /* guard bits of the state (NUM-7) */

/* Add 1 to a counter without wrapping. */
static void count_up(uint32_t *c)
{
    if (*c != UINT32_MAX) {
        *c += 1u;
    }
}

/* floor(x / 2^n), the ">>" of spec section 0, for either sign (0 <= n <= 62).
 * For x < 0: floor(x / 2^n) = -(((-x - 1) >> n)) - 1, where -x - 1 = -(x + 1) >= 0
 * never overflows (also for INT64_MIN). Compilers fold this to one SAR/ASR. */
int64_t bd_shr_floor(int64_t x, unsigned n)
{
    if (x >= 0) {
        return (int64_t)((uint64_t)x >> n);
    }
    return -(int64_t)((uint64_t)(-(x + 1)) >> n) - 1;
}

/* NUM-2: Q24 x Q24, round to nearest, ties toward +inf. The caller keeps a*b + 2^23
 * within int64 (XI-2: |W| <= 2^31, |difference| < 2^32; CTRL-3: both < 2^32). */
int64_t bd_mulq(int64_t a, int64_t b)
{
    return bd_shr_floor(a * b + ((int64_t)1 << (Q - 1u)), Q);
}

/* NUM-7: sat54, counted (NUM-3: only a clamp counts). */
int64_t bd_sat54(int64_t x, uint32_t *count)
{
    if (x > BD_STATE_MAX) {
        count_up(count);
        return BD_STATE_MAX;
    }
    if (x < BD_STATE_MIN) {
        count_up(count);
        return BD_STATE_MIN;
    }
    return x;
}

/* sat32 (section 0), counted. */
int32_t bd_sat32(int64_t x, uint32_t *count)
{
    if (x > (int64_t)INT32_MAX) {
        count_up(count);
        return INT32_MAX;
    }
    if (x < (int64_t)INT32_MIN) {
        count_up(count);
        return INT32_MIN;
    }
    return (int32_t)x;
}

/* NUM-8: (x + 2^29) >> 30; fits int32 for every sat54'd x (|x| <= 2^61, no overflow). */
int32_t bd_wire(int64_t x)
{
    return (int32_t)bd_shr_floor(x + ((int64_t)1 << (GUARD - 1u)), GUARD);
}

/* NUM-5: exact floor of the square root, digit by digit (no floating point). */
uint64_t bd_isqrt_u64(uint64_t x)
{
    uint64_t rem = x;
    uint64_t root = 0u;
    uint64_t bit = (uint64_t)1 << 62;

    while (bit > rem) {
        bit >>= 2;
    }
    while (bit != 0u) {
        if (rem >= (root + bit)) {
            rem -= root + bit;
            root = (root >> 1) + bit;
        } else {
            root >>= 1;
        }
        bit >>= 2;
    }
    return root;
}

/* CTRL-3: |v|^(p/2^n) as a Q24 word: n square roots, then p - 1 products; no
 * saturation (the result is < 2^31). |v| <= 2^31, so r << 24 <= 2^55. */
int64_t bd_fpow(int32_t v, uint32_t pow_num, uint32_t pow_sqrts)
{
    uint64_t r = (v < 0) ? (uint64_t)(-(int64_t)v) : (uint64_t)v;
    int64_t out;
    uint32_t i;

    for (i = 0u; i < pow_sqrts; ++i) {
        r = bd_isqrt_u64(r << Q);
    }
    out = (int64_t)r;
    for (i = 1u; i < pow_num; ++i) {
        out = bd_mulq(out, (int64_t)r);
    }
    return out;
}

int bd_ctrl_config_check(const bd_ctrl_config *cfg)
{
    if ((cfg->kind < BD_KIND_PC) || (cfg->kind > BD_KIND_FT)) {
        return BD_ERR_KIND;
    }
    if ((cfg->kts < 0) || (cfg->hts < 0) || (cfg->tsq < 0)) {
        return BD_ERR_GAIN;
    }
    if (cfg->band < 0) {
        return BD_ERR_BAND;
    }
    if ((cfg->kind == BD_KIND_FT)
        && ((cfg->pow_sqrts < 1u) || (cfg->pow_sqrts > 4u) || ((cfg->pow_num & 1u) == 0u)
            || (cfg->pow_num >= (1u << cfg->pow_sqrts)))) {
        return BD_ERR_EXPONENT;
    }
    return BD_OK;
}

/* CTRL-4: lambda = q24(x) * 2^30 (a multiplication: << of a negative is undefined). */
void bd_ctrl_init(bd_ctrl_state *s, int32_t lambda0_q24)
{
    s->lam = (int64_t)lambda0_q24 * ((int64_t)1 << GUARD);
    s->nu = 0;
    s->xi_prev = 0;
    s->armed = 1;
    s->since_reset = 0u;
    s->resets = 0u;
    s->saturations = 0u;
}

int32_t bd_ctrl_wire_lambda(const bd_ctrl_state *s)
{
    return bd_wire(s->lam);
}

/* STEP-2, STEP-3: the reset decision of the PI family, from the old state. */
static int reset_now(const bd_ctrl_config *cfg, const bd_ctrl_state *s, int32_t xi)
{
    int crossed = ((s->xi_prev > 0) && (xi <= 0)) || ((s->xi_prev < 0) && (xi >= 0));

    switch (cfg->kind) {
    case BD_KIND_RESET:
        return crossed && (s->armed != 0);
    case BD_KIND_DWELL:
        return crossed && (s->armed != 0) && (s->since_reset >= cfg->dwell);
    default:
        return 0;
    }
}

void bd_ctrl_step(const bd_ctrl_config *cfg, bd_ctrl_state *s, int32_t xi,
                  bd_step_out *out)
{
    int64_t dlam;
    int64_t nu_next = 0;          /* STEP-10, STEP-11: nu' = 0 for pc and ft */
    int32_t armed_next = s->armed;
    int reset = 0;
    uint32_t sats = s->saturations;

    if (cfg->kind == BD_KIND_PC) {
        /* STEP-10 */
        dlam = bd_sat54(-((int64_t)cfg->kts * xi), &sats);
    } else if (cfg->kind == BD_KIND_FT) {
        /* STEP-11: |KTS * fpow| <= (2^31 - 1) * 2^31 < 2^62 */
        int64_t mag = (int64_t)cfg->kts * bd_fpow(xi, cfg->pow_num, cfg->pow_sqrts);
        dlam = bd_sat54((xi > 0) ? -mag : ((xi < 0) ? mag : 0), &sats);
    } else {
        int64_t nu_used;
        int64_t abs_xi = (xi < 0) ? -(int64_t)xi : (int64_t)xi;  /* BAND-3: 64-bit */

        reset = reset_now(cfg, s, xi);                      /* STEP-2, STEP-3 */
        nu_used = (reset != 0) ? 0 : s->nu;                        /* STEP-4 */
        armed_next = ((reset == 0) && ((s->armed != 0) || (abs_xi > (int64_t)cfg->band)))
                     ? 1 : 0;                              /* STEP-5 */
        /* STEP-6: two exact 32x32->64 products, one sum, one negation (NUM-7) */
        dlam = bd_sat54(-(((int64_t)cfg->kts * xi) + ((int64_t)cfg->hts * bd_wire(nu_used))),
                        &sats);
        nu_next = bd_sat54(nu_used + (int64_t)cfg->tsq * xi, &sats);  /* STEP-7 */
    }
    /* STEP-1 / STEP-8: at most 3 clamps counted per step (STEP-9) */
    s->lam = bd_sat54(s->lam + dlam, &sats);
    s->nu = nu_next;
    s->xi_prev = xi;
    s->armed = armed_next;
    if (reset != 0) {
        s->since_reset = 1u;
        count_up(&s->resets);
    } else {
        count_up(&s->since_reset);
    }
    s->saturations = sats;
    if (out != NULL) {
        out->dlam = dlam;
        out->reset = reset;
    }
}

void bd_ctrl_run(const bd_ctrl_config *cfg, bd_ctrl_state *s, const int32_t *xi,
                 size_t n, bd_step_record *rec)
{
    size_t t;
    bd_step_out o;

    for (t = 0u; t < n; ++t) {
        bd_ctrl_step(cfg, s, xi[t], &o);
        if (rec != NULL) {
            rec[t].state = *s;
            rec[t].out = o;
        }
    }
}

/* XI-2: acc = (PIN != 0 ? mulq(PIN, L - rho) : 0) + sum mulq(W_j, L - lambda_j), every
 * difference and the sum exact in int64; XI-3: xi = sat32(acc), counted in sat_xi. */
int32_t bd_xi(int32_t lam_wire, int32_t pin, int32_t rho, const int32_t *weights,
              const int32_t *lam_j, size_t n, uint32_t *sat_count)
{
    int64_t acc = 0;
    size_t j;

    if (pin != 0) {
        acc = bd_mulq(pin, (int64_t)lam_wire - rho);
    }
    for (j = 0u; j < n; ++j) {
        acc += bd_mulq(weights[j], (int64_t)lam_wire - lam_j[j]);
    }
    return bd_sat32(acc, sat_count);
}

/* WMSR-1, WMSR-2: drop up to f terms whose lambda_j is strictly above lam_wire (the
 * largest lambda_j first, of equal ones the largest weight) and up to f strictly below
 * (the smallest first, then the largest weight). A removed term is overwritten by the
 * last one: the order changes, the sum bd_xi takes of the rest does not. O(f n). */
size_t bd_wmsr_trim(int32_t lam_wire, uint32_t f, int32_t *weights, int32_t *lam_j, size_t n)
{
    int side;

    for (side = 0; side < 2; ++side) {
        uint32_t dropped;
        for (dropped = 0u; dropped < f; ++dropped) {
            size_t j;
            size_t pick = n;
            for (j = 0u; j < n; ++j) {
                int outside = (side == 0) ? (lam_j[j] > lam_wire) : (lam_j[j] < lam_wire);
                if (outside == 0) {
                    continue;
                }
                if (pick == n) {
                    pick = j;
                } else {
                    int further = (side == 0) ? (lam_j[j] > lam_j[pick])
                                              : (lam_j[j] < lam_j[pick]);
                    if (further || ((lam_j[j] == lam_j[pick]) && (weights[j] > weights[pick]))) {
                        pick = j;
                    }
                }
            }
            if (pick == n) {
                break;  /* no more terms on this side */
            }
            n--;
            weights[pick] = weights[n];
            lam_j[pick] = lam_j[n];
        }
    }
    return n;
}
