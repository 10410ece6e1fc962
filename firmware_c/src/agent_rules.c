/*
 * The content rules of an authentic input (docs/firmware-spec.md section 11): the price
 * and its plausibility (PRICE-1..6), a neighbour's λ (LAM-1..2, LIVE-1), the commands
 * (CMD-1..6) and the plant's status (STATE-5, SAFE-1). Called by the receive path
 * (agent_rx.c) once a frame has decoded and verified; a rule that refuses a value counts
 * it and records the last safety rejection.
 */
#include "bessded/agent.h"

#include "agent_internal.h"

static void safety_reject(bd_agent *a, int cause, uint32_t safety_cause, uint32_t id)
{
    a->last_safety_cause = safety_cause;
    a->last_safety_sender = id;
    a->safety_rejections++;
    bd_count_add(a, cause, 1u, id);
}

static int lambda_ok(const bd_agent *a, int32_t raw)
{
    return a->p.lambda_min <= raw && raw <= a->p.lambda_max;
}

/* Track a price level beyond the step limit: consecutive frames carrying it. */
static uint32_t candidate(bd_agent *a, int has, int32_t rho)
{
    if (!has || !a->has_candidate || rho != a->candidate) {
        a->has_candidate = (uint8_t)has;
        a->candidate = rho;
        a->candidate_n = 0u;
    }
    if (has) {
        a->candidate_n++;
    }
    return a->candidate_n;
}

static int64_t abs64(int64_t x)
{
    return x < 0 ? -x : x;
}

/* PRICE-1..6 */
int bd_on_price(bd_agent *a, const bd_price_msg *m, uint32_t id, int64_t t)
{
    if (m->price_valid == 0u) {
        return 0;
    }
    if (!lambda_ok(a, m->rho)) {
        return -1;
    }
    if (m->rho < a->p.rho_min || m->rho > a->p.rho_max) {
        (void)candidate(a, 0, 0);
        safety_reject(a, BD_C_IMPLAUSIBLE_PRICE, BD_SAFETY_CAUSE_IMPLAUSIBLE_PRICE, id);
        return 0;
    }
    if (a->has_price && abs64((int64_t)m->rho - a->price) > a->p.price_step_max) {
        if (candidate(a, 1, m->rho) < a->p.price_persist) {
            safety_reject(a, BD_C_IMPLAUSIBLE_PRICE, BD_SAFETY_CAUSE_IMPLAUSIBLE_PRICE, id);
            return 0;
        }
        bd_count_add(a, BD_C_PRICE_STEPS_ACCEPTED, 1u, id);
    }
    (void)candidate(a, 0, 0);
    a->price = m->rho;
    a->has_price = 1;
    a->price_rx = t;
    a->has_price_rx = 1;
    return 0;
}

/* rne(dt / period) for dt >= 0, at least 1 (LAM-1) */
static int64_t samples_between(int64_t dt, int64_t period)
{
    if (dt < 0) {
        return 1;
    }
    int64_t q = dt / period;
    int64_t r2 = 2 * (dt % period);
    if (r2 > period || (r2 == period && (q & 1) != 0)) {
        q++;
    }
    return q < 1 ? 1 : q;
}

/* LAM-1..2, LIVE-1 */
int bd_on_mc(bd_agent *a, uint32_t j, const bd_mc_msg *m, uint32_t id, int64_t t)
{
    bd_neighbour *n = &a->nb[j];
    if (!lambda_ok(a, m->lambda)) {
        return -1;
    }
    if ((n->flags & (BD_NB_ALIVE | BD_NB_HAS_LAM | BD_NB_HAS_RX))
            == (BD_NB_ALIVE | BD_NB_HAS_LAM | BD_NB_HAS_RX)
        && active(n->state) && active(m->state)) {
        int64_t samples = samples_between(t - n->last_rx, a->p.period_ns);
        if (abs64((int64_t)m->lambda - n->lam) > samples * (int64_t)a->p.lambda_step_max) {
            safety_reject(a, BD_C_IMPLAUSIBLE_LAMBDA, BD_SAFETY_CAUSE_IMPLAUSIBLE_LAMBDA, id);
            return 0;
        }
    }
    n->lam = m->lambda;
    n->state = (uint8_t)m->state;
    n->last_rx = t;
    n->flags |= BD_NB_HAS_LAM | BD_NB_HAS_RX;
    return 0;
}

/* CMD-5: KTS' = rne-up(GainK_raw * TSQ / D), D = 1/scale; -1 if refused */
static int32_t gain_q30(uint32_t raw, int32_t tsq)
{
    int64_t num = 2 * (int64_t)raw * tsq + BD_GAIN_SCALE_DIV;
    int64_t q = num / (2 * BD_GAIN_SCALE_DIV);
    return q > INT32_MAX ? -1 : (int32_t)q;
}

/* CMD-1..7 */
int bd_on_command(bd_agent *a, const bd_command_msg *m, uint32_t id)
{
    if (m->target != a->p.id) {
        return 0;
    }
    bd_count_add(a, BD_C_COMMANDS, 1u, id);
    if (m->command == BD_CMD_ISOLATE) {
        bd_count_add(a, BD_C_COMMANDS_ISOLATE, 1u, id);
        if (a->state != BD_STATE_ISOLATED) {
            bd_set_state(a, BD_STATE_ISOLATED);
            bd_ctrl_init(&a->cs, a->p.idle_lambda);
        }
    } else if (m->command == BD_CMD_RECONNECT) {
        bd_count_add(a, BD_C_COMMANDS_RECONNECT, 1u, id);
        if (a->state == BD_STATE_ISOLATED) {
            bd_set_state(a, BD_STATE_INIT);
        }
    } else if (m->command == BD_CMD_PIN) {   /* CMD-7: the decoder checked GainK, GainH */
        a->pinned = m->gain_k == BD_PIN_ON ? 1 : 0;
    } else {   /* BD_CMD_SET_GAINS: the decoder checked the range */
        if (m->gain_k < a->p.gain_k_raw_min || m->gain_k > a->p.gain_k_raw_max
            || m->gain_h < a->p.gain_h_raw_min || m->gain_h > a->p.gain_h_raw_max) {
            safety_reject(a, BD_C_IMPLAUSIBLE_GAINS, BD_SAFETY_CAUSE_IMPLAUSIBLE_GAINS, id);
            return 0;
        }
        int needs_h = a->ctrl.kind == BD_KIND_PI || a->ctrl.kind == BD_KIND_RESET
                      || a->ctrl.kind == BD_KIND_DWELL;
        int32_t kts = gain_q30(m->gain_k, a->ctrl.tsq);
        int32_t hts = gain_q30(m->gain_h, a->ctrl.tsq);
        if (m->gain_k == 0u || kts <= 0 || hts < 0 || (needs_h && m->gain_h == 0u)
            || (m->gain_h != 0u && hts == 0)) {
            return -1;
        }
        a->ctrl.kts = kts;
        a->ctrl.hts = hts;
        a->cs.nu = 0;
    }
    return 0;
}

/* STATE-5, SAFE-1 */
void bd_on_status(bd_agent *a, const bd_status_msg *m, uint32_t id, int64_t t)
{
    int fault = m->fault_over_current != 0u || m->fault_voltage != 0u;
    if (fault && !a->plant_fault) {
        bd_count_add(a, BD_C_PLANT_FAULTS, 1u, id);
    }
    a->plant_fault = (uint8_t)fault;
    a->power_limited = (uint8_t)(m->power_limited != 0u || m->fault_soc != 0u);
    a->status_rx = t;
    a->has_status_rx = 1;
}
