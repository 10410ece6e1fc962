/*
 * What the agent reports (include/bessded/agent.h): its counters and their names
 * (sections 10-13, firmware_py's names), the values of the AGENT_<i>_Diag pages (section 9.2,
 * DIAG-1..3), the IDs an acceptance filter must pass (GEN-5, AUTH-19), and the accessors
 * and sizes the bindings read. firmware_c/gen_contract.py checks that diag_value below
 * maps every Diag signal of the DBC.
 */
#include "bessded/agent.h"

#include <string.h>

#include "agent_internal.h"

const char *bd_counter_name(int counter)
{
    return (counter >= 0 && counter < BD_C_COUNT) ? bd_counter_names[counter] : NULL;
}

size_t bd_agent_size(void)
{
    return sizeof(bd_agent);
}

size_t bd_agent_params_size(void)
{
    return sizeof(bd_agent_params);
}

size_t bd_keyring_size(void)
{
    return sizeof(bd_keyring);
}

uint32_t bd_agent_counter(const bd_agent *a, int counter)
{
    return (counter >= 0 && counter < BD_C_COUNT) ? a->count[counter] : 0u;
}

uint32_t bd_agent_state(const bd_agent *a)
{
    return a->state;
}

int32_t bd_agent_fatal(const bd_agent *a)
{
    return a->fatal;
}

uint32_t bd_agent_boot(const bd_agent *a)
{
    return a->boot;
}

uint32_t bd_agent_resets(const bd_agent *a)
{
    return a->cs.resets;
}

/* ------------------------------------------------------------------ counting */

void bd_count_add(bd_agent *a, int c, uint32_t n, uint32_t frame_id)
{
    uint32_t v = a->count[c];
    a->count[c] = (n > UINT32_MAX - v) ? UINT32_MAX : v + n;
    if (a->on_event != NULL && n > 0u) {
        a->on_event(a->event_ctx, c, frame_id, a->count[c]);
    }
}

void bd_agent_note(bd_agent *a, int counter, uint32_t n)
{
    if (counter >= 0 && counter < BD_C_COUNT) {
        bd_count_add(a, counter, n, 0u);
    }
}

/* ------------------------------------------------------------------ Diag pages */

static uint32_t sat_u(uint64_t v, uint32_t max)
{
    return v > max ? max : (uint32_t)v;
}

/* DIAG-1..3: the value of an AGENT_<i>_Diag signal (BD_DIAG_SIG_*), before saturation */
static uint64_t diag_value(const bd_agent *a, uint32_t signal)
{
    const uint32_t *c = a->count;
    uint64_t alive = 0u;
    switch (signal) {
    case BD_DIAG_SIG_RESETS: return a->cs.resets;
    case BD_DIAG_SIG_DEADLINEMISSES: return c[BD_C_DEADLINE_MISS];
    case BD_DIAG_SIG_NEIGHBOURSALIVE:
        for (uint32_t j = 0u; j < a->p.n_neighbours; ++j) {
            alive += ((a->nb[j].flags & BD_NB_ALIVE) != 0u && active(a->nb[j].state)) ? 1u : 0u;
        }
        return alive;
    case BD_DIAG_SIG_STATE: return a->state;
    case BD_DIAG_SIG_REJECTEDDLC: return c[BD_C_DLC];
    case BD_DIAG_SIG_REJECTEDRANGE: return c[BD_C_RANGE];
    case BD_DIAG_SIG_REJECTEDUNKNOWNID: return c[BD_C_UNKNOWN_ID];
    case BD_DIAG_SIG_REJECTEDIMPERSONATION: return c[BD_C_IMPERSONATION];
    case BD_DIAG_SIG_LOSTFRAMES: return c[BD_C_LOST_FRAMES];
    case BD_DIAG_SIG_SATURATIONS: return (uint64_t)c[BD_C_SATURATIONS] + a->cs.saturations;
    case BD_DIAG_SIG_NEIGHBOURTIMEOUTS: return c[BD_C_NEIGHBOUR_TIMEOUTS];
    case BD_DIAG_SIG_PRICETIMEOUTS: return c[BD_C_PRICE_TIMEOUTS];
    case BD_DIAG_SIG_STATUSTIMEOUTS: return c[BD_C_STATUS_TIMEOUTS];
    case BD_DIAG_SIG_PLANTFAULTS: return c[BD_C_PLANT_FAULTS];
    case BD_DIAG_SIG_FOREIGNFRAMES: return c[BD_C_FOREIGN];
    case BD_DIAG_SIG_FOREIGNIDS: return c[BD_C_FOREIGN_ID];
    case BD_DIAG_SIG_UNTRUSTED: return c[BD_C_UNTRUSTED_SOURCES];
    case BD_DIAG_SIG_IMPLAUSIBLEPRICE: return c[BD_C_IMPLAUSIBLE_PRICE];
    case BD_DIAG_SIG_IMPLAUSIBLELAMBDA: return c[BD_C_IMPLAUSIBLE_LAMBDA];
    case BD_DIAG_SIG_IMPLAUSIBLEGAINS: return c[BD_C_IMPLAUSIBLE_GAINS];
    case BD_DIAG_SIG_SAFETYSENDER: return a->last_safety_sender;
    case BD_DIAG_SIG_SAFETYCAUSE: return a->last_safety_cause;
    case BD_DIAG_SIG_REJECTEDAUTH: return c[BD_C_AUTH];
    case BD_DIAG_SIG_UNSYNCED: return c[BD_C_UNSYNCED];
    case BD_DIAG_SIG_RESYNCS: return c[BD_C_RESYNCS];
    /* reserved slots (DIAG-1; the DBC marks them, firmware_py contract.DIAG_RESERVED):
     * always 0, they counted checks of E2E-only frames the DBC no longer has */
    case BD_DIAG_SIG_REJECTEDCRC:
    case BD_DIAG_SIG_REPEATEDCOUNTER:
    case BD_DIAG_SIG_INTERLEAVEDCOUNTERS:
        return 0u;
    default: return 0u;   /* unreachable: gen_contract.py refuses an unmapped signal */
    }
}

/* DIAG-1..3: page `page`'s values, v[k] for its field k */
void bd_diag_page(const bd_agent *a, uint32_t page, uint32_t *v)
{
    for (uint32_t k = 0u; k < bd_diag_page_signals[page]; ++k) {
        /* counters saturate at their signal's maximum, they never wrap */
        const bd_diag_field *f = &bd_diag_pages[page][k];
        v[k] = sat_u(diag_value(a, f->signal), f->max);
    }
}

/* ------------------------------------------------------------------ acceptance filter */

static void insert_sorted(uint32_t *ids, size_t *n, size_t max, uint32_t id)
{
    size_t k = 0u;
    while (k < *n && ids[k] < id) {
        k++;
    }
    if ((k < *n && ids[k] == id) || *n >= max) {
        return;
    }
    memmove(&ids[k + 1u], &ids[k], (*n - k) * sizeof ids[0]);
    ids[k] = id;
    (*n)++;
}

size_t bd_agent_accepted_ids(const bd_agent *a, uint32_t *ids, size_t max)
{
    size_t n = 0u;
    for (int k = 0; k < BD_N_ECHO; ++k) {
        insert_sorted(ids, &n, max, a->echo[k].id);
    }
    for (uint32_t r = 0u; r < a->n_rx; ++r) {
        insert_sorted(ids, &n, max, a->rx[r].id);
        insert_sorted(ids, &n, max, a->rx[r].sync_id);
    }
    if (a->p.signed_price != 0u) {   /* AUTH-32: the router's price signatures */
        insert_sorted(ids, &n, max, BD_ER_PRICESIG_ID);
    }
    for (int k = 0; k < BD_N_SYNC_IDS; ++k) {   /* peers: keys held beyond the inputs' */
        uint32_t sid = bd_sync_ids[k];
        uint32_t sender = bd_id_sender(sid);
        int taken = sender == a->p.id;
        for (uint32_t r = 0u; r < a->n_rx && !taken; ++r) {
            taken = bd_id_sender(a->rx[r].id) == sender;
        }
        int held = 0;
        for (uint32_t q = 0u; q < a->n_listed && !held; ++q) {
            held = a->key_label[q] == sender;
        }
        if ((sid > BD_SETPOINT_SYNC_BASE && sid <= BD_SETPOINT_SYNC_BASE + BD_N_AGENTS_MAX)
            || (sid > BD_STATUS_SYNC_BASE && sid <= BD_STATUS_SYNC_BASE + BD_N_AGENTS_MAX)) {
            held = 0;   /* AUTH-28: another agent's link frame, under a key it lacks */
        }
        if (!taken && held && (a->p.fleet_size == 0u || bd_id_agent(sid) <= a->p.fleet_size)) {
            insert_sorted(ids, &n, max, sid);
        }
    }
    return n;
}
