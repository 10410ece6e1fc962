/*
 * The agent runtime (include/bessded/agent.h): firmware_py/runtime.py and the agent's
 * side of firmware_py/nodeio.py, rule for rule (docs/firmware-spec.md sections 7-14).
 * Integers only; times are int64 ns.
 */
#include "bessded/agent.h"

#include <string.h>

#include "frames.h"

#define LABEL_PLANT (BD_N_AGENTS_MAX + 1u)
#define LABEL_ROUTER (BD_N_AGENTS_MAX + 2u)
#define FV_WINDOW (1u << BD_FV_TX_BITS)
#define COUNT_MAX ((1u << BD_FV_COUNT_BITS) - 1u)
#define BOOT_MAX ((1u << BD_FV_BOOT_BITS) - 1u)
#define FV_MAX ((UINT64_C(1) << (BD_FV_BOOT_BITS + BD_FV_COUNT_BITS)) - 1u)
#define LOST_WINDOWS 8u     /* windows tried after a sender timed out (AUTH-10) */
#define STALE_WINDOWS 1u    /* past windows tried before a frame is forged (AUTH-25) */
#define INSECURE_BOOT 1u
#define ECHO_MC 0
#define ECHO_SETPOINT 1
#define ECHO_DIAG 2
#define ECHO_MC_SYNC 3
#define ECHO_SETPOINT_SYNC 4
#define ECHO_DIAG_SYNC 5
#define N_SECURED_TX 3          /* own secured IDs: MC, Setpoint, Diag (tx_count index) */

/* AUTH-7: the one join and split of a freshness value, Boot ‖ Count (the DBC's sizes). */
static uint64_t fv_join(uint32_t boot, uint32_t count)
{
    return ((uint64_t)boot << BD_FV_COUNT_BITS) | count;
}

static uint32_t fv_boot(uint64_t fv)
{
    return (uint32_t)(fv >> BD_FV_COUNT_BITS);
}

static const char *const counter_names[BD_C_COUNT] = {
    "crc", "dlc", "range", "unknown_id", "malformed", "impersonation", "repeated_counter",
    "lost_frames", "saturations", "neighbour_timeouts", "price_timeouts", "status_timeouts",
    "plant_faults", "foreign", "foreign_id", "counter_jump", "counter_clash",
    "untrusted_sources", "untrusted", "implausible_price", "implausible_lambda",
    "implausible_gains", "auth", "unsynced", "resyncs", "deadline_miss", "send_failure",
    "error_frame", "commands", "commands_isolate", "commands_reconnect",
    "price_steps_accepted", "setpoint_limited", "not_a_frame", "invalid_frame", "rx_error",
    "stale", "joining"};

const char *bd_counter_name(int counter)
{
    return (counter >= 0 && counter < BD_C_COUNT) ? counter_names[counter] : NULL;
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

static void add(bd_agent *a, int c, uint32_t n, uint32_t frame_id)
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
        add(a, counter, n, 0u);
    }
}

static void set_state(bd_agent *a, uint32_t state)
{
    a->state = state;
    if (a->on_event != NULL) {
        a->on_event(a->event_ctx, BD_EV_STATE, 0u, state);
    }
}

/* ------------------------------------------------------------------ the contract's IDs */

static int in_block(uint32_t id, uint32_t base)
{
    return id > base && id <= base + BD_N_AGENTS_MAX;
}

/* The agent a per-agent ID belongs to (AGENT_<i>_*, PLANT_<i>_*), 0 for the router's. */
static uint32_t agent_of(uint32_t id)
{
    static const uint32_t bases[] = {BD_MC_BASE, BD_SETPOINT_BASE, BD_STATUS_BASE,
                                     BD_DIAG_BASE, BD_MC_SYNC_BASE, BD_SETPOINT_SYNC_BASE,
                                     BD_STATUS_SYNC_BASE, BD_DIAG_SYNC_BASE};
    for (size_t k = 0u; k < sizeof bases / sizeof bases[0]; ++k) {
        if (in_block(id, bases[k])) {
            return id - bases[k];
        }
    }
    return 0u;
}

/* The key label code of a frame's DBC sender: 1..32 an agent, plant, router. */
static uint32_t sender_of(uint32_t id)
{
    if (in_block(id, BD_STATUS_BASE) || in_block(id, BD_STATUS_SYNC_BASE)) {
        return LABEL_PLANT;
    }
    uint32_t i = agent_of(id);
    return i != 0u ? i : LABEL_ROUTER;
}

static int dbc_known(uint32_t id)
{
    return id < 0x800u && (bd_dbc_ids[id / 8u] & (1u << (id % 8u))) != 0u;
}

static int sync_index(uint32_t id)
{
    int lo = 0;
    int hi = BD_N_SYNC_IDS - 1;
    while (lo <= hi) {
        int mid = (lo + hi) / 2;
        uint32_t m = bd_sync_ids[mid];
        if (m == id) {
            return mid;
        }
        if (m < id) {
            lo = mid + 1;
        } else {
            hi = mid - 1;
        }
    }
    return -1;
}

/* ------------------------------------------------------------------ keys */

static int starts_with(const char *s, const char *prefix)
{
    while (*prefix != '\0') {
        if (*s++ != *prefix++) {
            return 0;
        }
    }
    return 1;
}

static uint32_t label_code(const char *s)
{
    if (starts_with(s, "plant") && s[5] == '\0') {
        return LABEL_PLANT;
    }
    if (starts_with(s, "router") && s[6] == '\0') {
        return LABEL_ROUTER;
    }
    if (!starts_with(s, "agent_") || s[6] < '1' || s[6] > '9') {
        return 0u;
    }
    uint32_t n = 0u;
    for (const char *c = s + 6; *c != '\0'; ++c) {
        if (*c < '0' || *c > '9' || n > BD_N_AGENTS_MAX) {
            return 0u;
        }
        n = n * 10u + (uint32_t)(*c - '0');
    }
    return n <= BD_N_AGENTS_MAX ? n : 0u;
}

static void label_text(uint32_t code, char out[BD_LABEL_MAX + 1])
{
    if (code == LABEL_PLANT) {
        memcpy(out, "plant", 6);
    } else if (code == LABEL_ROUTER) {
        memcpy(out, "router", 7);
    } else {
        memcpy(out, "agent_", 6);
        if (code >= 10u) {
            out[6] = (char)('0' + code / 10u);
            out[7] = (char)('0' + code % 10u);
            out[8] = '\0';
        } else {
            out[6] = (char)('0' + code);
            out[7] = '\0';
        }
    }
}

/* The index of label's key in a->key, deriving it in insecure mode; -1 if not held. */
static int key_of(bd_agent *a, uint32_t label)
{
    for (uint32_t k = 0u; k < a->n_keys; ++k) {
        if (a->key_label[k] == label) {
            return (int)k;
        }
    }
    if (!a->derive || a->n_keys >= BD_MAX_PEERS) {
        return -1;
    }
    char text[BD_LABEL_MAX + 1];
    label_text(label, text);
    if (bd_derive_node_key(a->master, text, a->key[a->n_keys]) != 0) {
        a->fatal = BD_ERR_CRYPTO;
        return -1;
    }
    a->key_label[a->n_keys] = (uint8_t)label;
    return (int)a->n_keys++;
}

static int new_boot(bd_agent *a)
{
    if (a->boot >= BOOT_MAX) {
        return BD_ERR_BOOT;
    }
    if (a->persist_boot != NULL && a->persist_boot(a->persist_ctx, a->boot + 1u) != 0) {
        return BD_ERR_BOOT;   /* write-ahead: durable before it is used */
    }
    a->boot += 1u;
    return BD_OK;
}

/* ------------------------------------------------------------------ init */

static void init_echo(bd_echo *e, uint32_t id)
{
    memset(e, 0, sizeof *e);
    e->id = (uint16_t)id;
}

int bd_agent_init(bd_agent *a, const bd_agent_params *p, const bd_keyring *keys,
                  bd_event_fn on_event, void *event_ctx)
{
    memset(a, 0, sizeof *a);
    if (p->id < 1u || p->id > BD_N_AGENTS_MAX || p->n_neighbours > BD_MAX_NEIGHBOURS
        || p->fleet_size > BD_N_AGENTS_MAX || p->period_ns <= 0
        || bd_ctrl_config_check(&p->ctrl) != BD_OK || keys->n_peers > BD_MAX_PEERS) {
        return BD_ERR_PARAMS;
    }
    a->p = *p;
    a->ctrl = p->ctrl;
    bd_ctrl_init(&a->cs, p->lambda0);
    a->state = BD_STATE_INIT;
    a->on_event = on_event;
    a->event_ctx = event_ctx;
    memcpy(a->own_key, keys->key, BD_KEY_BYTES);
    a->boot = keys->boot;
    a->persist_boot = keys->persist_boot;
    a->persist_ctx = keys->persist_ctx;
    a->insecure = keys->insecure;
    a->derive = keys->insecure || keys->has_master;
    if (keys->has_master && !keys->insecure) {
        memcpy(a->master, keys->master, BD_KEY_BYTES);
    }   /* insecure: the public all-zero master (memset above) */
    for (uint32_t k = 0u; k < keys->n_peers; ++k) {
        uint32_t code = label_code(keys->peer_label[k]);
        if (code == 0u) {
            return BD_ERR_PARAMS;
        }
        a->key_label[a->n_keys] = (uint8_t)code;
        a->key_floor[a->n_keys] = a->insecure ? 0u : keys->peer_floor[k];
        memcpy(a->key[a->n_keys], keys->peer_key[k], BD_KEY_BYTES);
        a->n_keys++;
    }
    /* inputs (RX-1): price, command, own status, neighbours' MC; each with its sender's key */
    uint32_t ids[BD_RX_MC0 + BD_MAX_NEIGHBOURS];
    uint32_t sync_ids[BD_RX_MC0 + BD_MAX_NEIGHBOURS];   /* each input's <name>_Sync */
    ids[BD_RX_PRICE] = BD_ER_PRICE_ID;
    sync_ids[BD_RX_PRICE] = BD_ER_PRICE_SYNC_ID;
    ids[BD_RX_COMMAND] = BD_ER_COMMAND_ID;
    sync_ids[BD_RX_COMMAND] = BD_ER_COMMAND_SYNC_ID;
    ids[BD_RX_STATUS] = BD_STATUS_BASE + p->id;
    sync_ids[BD_RX_STATUS] = BD_STATUS_SYNC_BASE + p->id;
    for (uint32_t j = 0u; j < p->n_neighbours; ++j) {
        ids[BD_RX_MC0 + j] = BD_MC_BASE + p->neighbour_id[j];
        sync_ids[BD_RX_MC0 + j] = BD_MC_SYNC_BASE + p->neighbour_id[j];
    }
    a->n_rx = BD_RX_MC0 + p->n_neighbours;
    for (uint32_t r = 0u; r < a->n_rx; ++r) {
        bd_rx_slot *s = &a->rx[r];
        s->id = (uint16_t)ids[r];
        s->sync_id = (uint16_t)sync_ids[r];
        int k = key_of(a, sender_of(ids[r]));
        if (k < 0) {
            return a->fatal != 0 ? a->fatal : BD_ERR_MISSING_KEY;
        }
        s->key_index = (uint8_t)k;
        if (a->insecure) {  /* every insecure sender runs at boot 1 from count 0 */
            s->flags = BD_RX_HAS_FV | BD_RX_LOST;
            s->fv = fv_join(INSECURE_BOOT, 0u) - 1u;
        }
    }
    /* the peer syncs the acceptance filter passes: keys held beyond the inputs' senders */
    a->n_listed = a->derive ? 0u : a->n_keys;
    init_echo(&a->echo[ECHO_MC], BD_MC_BASE + p->id);
    init_echo(&a->echo[ECHO_SETPOINT], BD_SETPOINT_BASE + p->id);
    init_echo(&a->echo[ECHO_DIAG], BD_DIAG_BASE + p->id);
    init_echo(&a->echo[ECHO_MC_SYNC], BD_MC_SYNC_BASE + p->id);
    init_echo(&a->echo[ECHO_SETPOINT_SYNC], BD_SETPOINT_SYNC_BASE + p->id);
    init_echo(&a->echo[ECHO_DIAG_SYNC], BD_DIAG_SYNC_BASE + p->id);
    a->sync_pending = 1;
    a->hello_after = INT64_MIN;
    a->join_until = INT64_MAX;
    a->joining = !a->insecure && p->join_ns > 0;   /* insecure: every state preset */
    return new_boot(a);   /* AUTH-3: before the first frame is signed */
}

/* ------------------------------------------------------------------ rejections */

static void reject(bd_agent *a, int cause, uint32_t id)
{
    add(a, cause, 1u, id);
}

static void foreign(bd_agent *a, int cause, uint32_t id)
{
    add(a, BD_C_FOREIGN, 1u, id);
    reject(a, cause, id);
}

static void safety_reject(bd_agent *a, int cause, uint32_t safety_cause, uint32_t id)
{
    a->last_safety_cause = safety_cause;
    a->last_safety_sender = id;
    a->safety_rejections++;
    reject(a, cause, id);
}

/* RX-13: an E2E failure (dlc, range, auth: each adds to the streak) on `id`, an
 * input's slot or a sync ID's streak. */
static void fail(bd_agent *a, bd_rx_slot *slot, uint32_t id, int cause, int64_t t)
{
    if (cause == BD_C_AUTH && a->fatal == BD_ERR_CRYPTO) {
        return;   /* the primitive failed: nothing was verified, and the agent stops */
    }
    reject(a, cause, id);
    if (cause == BD_C_AUTH) {
        a->last_safety_cause = BD_SAFETY_CAUSE_AUTH;
        a->last_safety_sender = id;
    }
    uint32_t streak = 0u;
    int s = -1;
    if (slot != NULL) {
        if (slot->streak < UINT16_MAX) {
            slot->streak++;
        }
        streak = slot->streak;
    } else {
        s = sync_index(id);
        if (s >= 0 && a->sync_streak[s] < UINT16_MAX) {
            a->sync_streak[s]++;
            streak = a->sync_streak[s];
        }
    }
    if (streak >= a->p.untrusted_after) {
        if (slot != NULL) {
            slot->streak = 0u;
            slot->flags |= BD_RX_UNTRUSTED;
            slot->untrusted_until = t + a->p.untrusted_ns;
        } else if (s >= 0) {
            a->sync_streak[s] = 0u;   /* syncs are never blocked: only the verdict counts */
        }
        add(a, BD_C_UNTRUSTED_SOURCES, 1u, id);
        a->last_safety_cause = BD_SAFETY_CAUSE_UNTRUSTED;
        a->last_safety_sender = id;
    }
}

/* ------------------------------------------------------------------ receive */

static bd_echo *echo_of(bd_agent *a, uint32_t id)
{
    for (int k = 0; k < BD_N_ECHO; ++k) {
        if (a->echo[k].id == id) {
            return &a->echo[k];
        }
    }
    return NULL;
}

static int echo_holds(const bd_echo *e, const bd_frame *f)
{
    if (f->len != 8u) {
        return 0;
    }
    for (uint32_t k = 0u; k < e->n; ++k) {
        if (memcmp(e->data[k], f->data, 8u) == 0) {
            return 1;
        }
    }
    return 0;
}

static void remember(bd_echo *e, const uint8_t d[8])
{
    memcpy(e->data[e->next], d, 8u);
    e->next = (uint8_t)((e->next + 1u) % BD_ECHO_DEPTH);
    if (e->n < BD_ECHO_DEPTH) {
        e->n++;
    }
}

static bd_rx_slot *slot_of(bd_agent *a, uint32_t id)
{
    for (uint32_t r = 0u; r < a->n_rx; ++r) {
        if (a->rx[r].id == id) {
            return &a->rx[r];
        }
    }
    return NULL;
}

static bd_rx_slot *slot_synced_by(bd_agent *a, uint32_t sync_id)
{
    for (uint32_t r = 0u; r < a->n_rx; ++r) {
        if (a->rx[r].sync_id == sync_id) {
            return &a->rx[r];
        }
    }
    return NULL;
}

/* 1 if the frame's MAC verifies under key; a failed primitive stops the agent. */
static int verifies(bd_agent *a, const uint8_t *key, uint32_t id, const uint8_t d[8],
                    uint64_t fv)
{
    int v = bd_frame_verifies(key, id, d, fv);
    if (v < 0) {
        a->fatal = BD_ERR_CRYPTO;
    }
    return v == 1;
}

/* AUTH-25: whether the frame of FV v <= s->fv was accepted (older than 16: yes). */
static int seen(const bd_rx_slot *s, uint64_t v)
{
    uint64_t back = s->fv - v;
    return back >= 16u || ((s->seen >> back) & 1u) != 0u;
}

/* AUTH-25: the accepted-frame bits after `last` moved on to `fv` (frame: 1 if a frame
 * of FV fv was accepted, 0 for a sync's fv - 1). */
static uint16_t seen_after(const bd_rx_slot *s, int had_fv, uint64_t fv, unsigned frame)
{
    uint64_t shift = had_fv ? fv - s->fv : 16u;
    uint32_t bits = shift < 16u ? (uint32_t)s->seen << shift : 0u;
    return (uint16_t)((bits | frame) & 0xFFFFu);
}

/* AUTH-25: 1 if a frame that failed the window verifies with one of the STALE_WINDOWS
 * most recent values at or below the last accepted one that no accepted frame carried:
 * its sender's, late. */
static int stale(bd_agent *a, bd_rx_slot *s, const bd_frame *f, uint32_t counter)
{
    uint64_t fv;
    if (bd_fv_past(s->fv, counter, BD_FV_TX_BITS, &fv) != 0) {
        return 0;
    }
    for (uint32_t k = 0u; k < STALE_WINDOWS; ++k, fv -= FV_WINDOW) {
        if (!seen(s, fv) && verifies(a, a->key[s->key_index], f->id, f->data, fv)) {
            s->seen = (uint16_t)(s->seen | (1u << (s->fv - fv)));   /* again: a replay */
            return 1;
        }
        if (fv < FV_WINDOW) {
            break;
        }
    }
    return 0;
}

/* AUTH-9..12: 1 if a decoded secured frame is authentic and fresh (and accepted). */
static int authentic(bd_agent *a, bd_rx_slot *s, const bd_frame *f, uint32_t counter,
                     int64_t t)
{
    if ((s->flags & BD_RX_HAS_FV) == 0u) {
        reject(a, a->joining ? BD_C_JOINING : BD_C_UNSYNCED, f->id);
        return 0;
    }
    uint32_t tries = (s->flags & BD_RX_LOST) != 0u ? LOST_WINDOWS : 1u;
    uint64_t fv;
    int found = 0;
    if (bd_fv_candidate(s->fv, counter, BD_FV_TX_BITS, FV_MAX, &fv) == 0) {
        for (; tries > 0u; --tries, fv += FV_WINDOW) {
            if (verifies(a, a->key[s->key_index], f->id, f->data, fv)) {
                found = 1;
                break;
            }
        }
    }
    if (!found) {
        if (stale(a, s, f, counter)) {
            reject(a, BD_C_STALE, f->id);   /* genuine but late: not used, not forged */
        } else if ((s->flags & BD_RX_LOST) != 0u) {
            reject(a, BD_C_UNSYNCED, f->id);
        } else {
            fail(a, s, f->id, BD_C_AUTH, t);
        }
        return 0;
    }
    uint64_t last = s->fv;
    if (fv <= FV_MAX) {
        s->seen = seen_after(s, 1, fv, 1u);
        s->fv = fv;
    }
    s->flags &= (uint8_t)~BD_RX_LOST;
    uint64_t gap = fv - last - 1u;
    add(a, BD_C_LOST_FRAMES, gap > UINT32_MAX ? UINT32_MAX : (uint32_t)gap, f->id);
    return 1;
}

/* AUTH-13..17: a sync of one of the agent's inputs. */
static void on_sync(bd_agent *a, bd_rx_slot *s, const bd_frame *f, int64_t t)
{
    bd_sync_msg m;
    if (f->len != 8u) {
        fail(a, NULL, f->id, BD_C_DLC, t);
        return;
    }
    if (bd_decode_sync(f->data, &m) != 0) {
        fail(a, NULL, f->id, BD_C_RANGE, t);
        return;
    }
    uint64_t fv = fv_join(m.boot, m.count);
    if (!verifies(a, a->key[s->key_index], f->id, f->data, fv)
        || m.boot < a->key_floor[s->key_index]) {   /* AUTH-21: an earlier run or boot */
        fail(a, NULL, f->id, BD_C_AUTH, t);
        return;
    }
    int k = sync_index(f->id);
    if (k >= 0) {
        a->sync_streak[k] = 0u;
    }
    if (a->joining) {   /* AUTH-26: keep the sender's newest sync until the window ends */
        if ((s->flags & BD_RX_JOIN) != 0u && fv < s->fv) {
            if (s->fv - fv < FV_WINDOW) {
                reject(a, BD_C_STALE, f->id);     /* late, as in AUTH-16 */
            } else {
                fail(a, NULL, f->id, BD_C_AUTH, t);   /* older than one already heard */
            }
            return;
        }
        if ((s->flags & BD_RX_JOIN) == 0u) {
            a->hello_due = 1;   /* a first contact: tell the peer our freshness now */
        }
        s->fv = fv;
        s->flags |= BD_RX_JOIN;
        return;
    }
    int has_fv = (s->flags & BD_RX_HAS_FV) != 0u;
    int restarted = !has_fv || fv_boot(s->fv + 1u) != m.boot;
    if (has_fv && fv - 1u <= s->fv) {
        if (fv - 1u == s->fv) {
            s->flags &= (uint8_t)~BD_RX_LOST;   /* in step with the sender */
            return;
        }
        if (!a->insecure) {   /* a genuine sync never goes back: a replay ... */
            if (s->fv - (fv - 1u) < FV_WINDOW) {
                reject(a, BD_C_STALE, f->id);   /* ... or its tick's frame overtook it */
            } else {
                fail(a, NULL, f->id, BD_C_AUTH, t);
            }
            return;
        }
        s->flags &= (uint8_t)~BD_RX_HAS_FV;   /* --insecure: a restarted sender is at boot 1 */
        restarted = 1;
    }
    if (fv - 1u <= FV_MAX) {
        s->seen = seen_after(s, (s->flags & BD_RX_HAS_FV) != 0u, fv - 1u, 0u);
        s->fv = fv - 1u;
        s->flags |= BD_RX_HAS_FV;
    }
    s->flags &= (uint8_t)~BD_RX_LOST;
    add(a, BD_C_RESYNCS, 1u, f->id);
    if (restarted) {
        a->hello_due = 1;
    }
}

/* AUTH-26: at the end of the join window, each input takes its sender's newest sync;
 * the frames of the window were not taken, so the input counts as lost (AUTH-13). */
static void settle(bd_agent *a, int64_t t)
{
    if (t < a->join_until) {
        return;
    }
    a->joining = 0;
    for (uint32_t r = 0u; r < a->n_rx; ++r) {
        bd_rx_slot *s = &a->rx[r];
        if ((s->flags & BD_RX_JOIN) == 0u) {
            continue;
        }
        uint64_t fv = s->fv;
        s->flags &= (uint8_t)~BD_RX_JOIN;
        if (fv - 1u <= FV_MAX) {
            s->seen = seen_after(s, 0, fv - 1u, 0u);
            s->fv = fv - 1u;
            s->flags |= BD_RX_HAS_FV;
        }
        s->flags |= BD_RX_LOST;
        add(a, BD_C_RESYNCS, 1u, s->sync_id);
    }
}

/* AUTH-19: a sync of a frame the agent does not use, from a node whose key it holds:
 * verified only to notice a peer's (re)start. 1 if it was such a sync. */
static int peer_sync(bd_agent *a, const bd_frame *f, int64_t t, int k)
{
    if (a->p.fleet_size != 0u && agent_of(f->id) > a->p.fleet_size) {
        return 0;
    }
    uint32_t label = sender_of(f->id);
    int key = (label == a->p.id) ? -2 : key_of(a, label);
    if (key == -1) {
        return 0;
    }
    bd_sync_msg m;
    if (f->len != 8u || bd_decode_sync(f->data, &m) != 0) {
        return 1;   /* not a usable sync; not this node's input either */
    }
    if (a->peer_boot[k] == m.boot) {
        return 1;
    }
    uint64_t fv = fv_join(m.boot, m.count);
    const uint8_t *kk = (key == -2) ? a->own_key : a->key[key];
    if (!verifies(a, kk, f->id, f->data, fv)
        || (key != -2 && m.boot < a->key_floor[key])) {   /* AUTH-21 */
        fail(a, NULL, f->id, BD_C_AUTH, t);
        return 1;
    }
    a->peer_boot[k] = (uint16_t)m.boot;
    a->hello_due = 1;
    return 1;
}

static void sender_lost(bd_rx_slot *s)
{
    s->flags |= BD_RX_LOST;
}

static int active(uint32_t state)
{
    return state == BD_STATE_RUNNING;
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
static int on_price(bd_agent *a, const bd_price_msg *m, uint32_t id, int64_t t)
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
        add(a, BD_C_PRICE_STEPS_ACCEPTED, 1u, id);
    }
    (void)candidate(a, 0, 0);
    a->price = m->rho;
    a->has_price = 1;
    a->price_segment = m->segment;
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
static int on_mc(bd_agent *a, uint32_t j, const bd_mc_msg *m, uint32_t id, int64_t t)
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

/* CMD-1..6 */
static int on_command(bd_agent *a, const bd_command_msg *m, uint32_t id)
{
    if (m->target != a->p.id) {
        return 0;
    }
    add(a, BD_C_COMMANDS, 1u, id);
    if (m->command == BD_CMD_ISOLATE) {
        add(a, BD_C_COMMANDS_ISOLATE, 1u, id);
        if (a->state != BD_STATE_ISOLATED) {
            set_state(a, BD_STATE_ISOLATED);
            bd_ctrl_init(&a->cs, a->p.idle_lambda);
        }
    } else if (m->command == BD_CMD_RECONNECT) {
        add(a, BD_C_COMMANDS_RECONNECT, 1u, id);
        if (a->state == BD_STATE_ISOLATED) {
            set_state(a, BD_STATE_INIT);
        }
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
static void on_status(bd_agent *a, const bd_status_msg *m, uint32_t id, int64_t t)
{
    int fault = m->fault_over_current != 0u || m->fault_voltage != 0u;
    if (fault && !a->plant_fault) {
        add(a, BD_C_PLANT_FAULTS, 1u, id);
    }
    a->plant_fault = (uint8_t)fault;
    a->power_limited = (uint8_t)(m->power_limited != 0u || m->fault_soc != 0u);
    a->status_rx = t;
    a->has_status_rx = 1;
}

static int decode_and_use(bd_agent *a, bd_rx_slot *s, const bd_frame *f, int64_t t)
{
    uint32_t r = (uint32_t)(s - a->rx);
    int bad;
    uint32_t counter;
    bd_price_msg pm;
    bd_command_msg cm;
    bd_status_msg sm;
    bd_mc_msg mm;
    switch (r) {
    case BD_RX_PRICE:
        bad = bd_decode_price(f->data, &pm);
        counter = pm.counter;
        break;
    case BD_RX_COMMAND:
        bad = bd_decode_command(f->data, &cm);
        counter = cm.counter;
        break;
    case BD_RX_STATUS:
        bad = bd_decode_status(f->data, &sm);
        counter = sm.counter;
        break;
    default:
        bad = bd_decode_mc(f->data, &mm);
        counter = mm.counter;
        break;
    }
    if (bad != 0) {
        fail(a, s, f->id, BD_C_RANGE, t);
        return 0;
    }
    if (!authentic(a, s, f, counter, t)) {
        return 0;
    }
    uint32_t before = a->safety_rejections;
    int err;
    switch (r) {
    case BD_RX_PRICE:
        err = on_price(a, &pm, f->id, t);
        break;
    case BD_RX_COMMAND:
        err = on_command(a, &cm, f->id);
        break;
    case BD_RX_STATUS:
        on_status(a, &sm, f->id, t);
        err = 0;
        break;
    default:
        err = on_mc(a, r - BD_RX_MC0, &mm, f->id, t);
        break;
    }
    if (err != 0) {
        fail(a, s, f->id, BD_C_RANGE, t);
        return 0;
    }
    if (a->safety_rejections == before) {
        s->streak = 0u;   /* valid and plausible: the E2E streak is over */
    }
    return 1;
}

void bd_agent_rx(bd_agent *a, const bd_frame *f, int64_t t)
{
    uint32_t id = f->id;
    if (a->joining) {
        settle(a, t);
    }
    if ((f->flags & BD_FRAME_EXT) != 0u) {
        reject(a, BD_C_UNKNOWN_ID, id);
        return;
    }
    if ((f->flags & (BD_FRAME_RTR | BD_FRAME_ERR | BD_FRAME_FD)) != 0u) {
        reject(a, BD_C_MALFORMED, id);
        return;
    }
    bd_echo *e = echo_of(a, id);
    if (e != NULL) {
        if (!echo_holds(e, f)) {
            foreign(a, BD_C_IMPERSONATION, id);
        }
        return;
    }
    bd_rx_slot *s = slot_of(a, id);
    if (s == NULL) {
        bd_rx_slot *synced = slot_synced_by(a, id);
        if (synced != NULL) {
            on_sync(a, synced, f, t);
            return;
        }
        int k = sync_index(id);
        if (k >= 0 && peer_sync(a, f, t, k)) {
            return;
        }
        if (!dbc_known(id)) {
            reject(a, BD_C_UNKNOWN_ID, id);
        } else if (a->p.fleet_size != 0u && agent_of(id) > a->p.fleet_size) {
            foreign(a, BD_C_FOREIGN_ID, id);
        }
        return;   /* a DBC frame that is not for this node */
    }
    if ((s->flags & BD_RX_UNTRUSTED) != 0u && t >= s->untrusted_until) {
        s->flags &= (uint8_t)~BD_RX_UNTRUSTED;   /* inputs are secured: frames prove themselves */
    }
    if (f->len != 8u) {
        fail(a, s, id, BD_C_DLC, t);
        return;
    }
    (void)decode_and_use(a, s, f, t);
}

/* ------------------------------------------------------------------ periodic */

static void update_neighbours(bd_agent *a, int64_t t)
{
    for (uint32_t j = 0u; j < a->p.n_neighbours; ++j) {
        bd_neighbour *n = &a->nb[j];
        int alive = (n->flags & BD_NB_HAS_RX) != 0u && t - n->last_rx <= a->p.neighbour_timeout_ns;
        if ((n->flags & BD_NB_ALIVE) != 0u && !alive) {
            add(a, BD_C_NEIGHBOUR_TIMEOUTS, 1u, a->rx[BD_RX_MC0 + j].id);
            sender_lost(&a->rx[BD_RX_MC0 + j]);
        }
        n->flags = (uint8_t)(alive ? (n->flags | BD_NB_ALIVE) : (n->flags & ~BD_NB_ALIVE));
    }
}

static void update_state(bd_agent *a)
{
    int64_t t = a->now;
    int price_ok = a->has_price_rx && t - a->price_rx <= a->p.price_timeout_ns;
    int status_ok = a->has_status_rx && t - a->status_rx <= a->p.status_timeout_ns;
    if (a->price_fresh && !price_ok) {
        add(a, BD_C_PRICE_TIMEOUTS, 1u, BD_ER_PRICE_ID);
        sender_lost(&a->rx[BD_RX_PRICE]);
    }
    if (a->status_fresh && !status_ok) {
        add(a, BD_C_STATUS_TIMEOUTS, 1u, a->rx[BD_RX_STATUS].id);
        sender_lost(&a->rx[BD_RX_STATUS]);
    }
    a->price_fresh = (uint8_t)price_ok;
    a->status_fresh = (uint8_t)status_ok;
    if (a->state == BD_STATE_ISOLATED) {
        return;
    }
    int healthy = price_ok && status_ok && !a->plant_fault;
    if (a->state == BD_STATE_RUNNING && !healthy) {
        set_state(a, BD_STATE_SAFE);
        a->cs.nu = 0;
        a->cs.xi_prev = 0;
    } else if ((a->state == BD_STATE_INIT || a->state == BD_STATE_SAFE) && healthy) {
        set_state(a, BD_STATE_RUNNING);
        a->cs.nu = 0;
        a->cs.xi_prev = 0;
    }
}

int32_t bd_agent_lambda(const bd_agent *a)
{
    return bd_ctrl_wire_lambda(&a->cs);
}

static void step(bd_agent *a)
{
    int32_t w[BD_MAX_NEIGHBOURS];
    int32_t lam[BD_MAX_NEIGHBOURS];
    size_t n = 0u;
    for (uint32_t j = 0u; j < a->p.n_neighbours; ++j) {
        const bd_neighbour *nb = &a->nb[j];
        if ((nb->flags & (BD_NB_ALIVE | BD_NB_HAS_LAM)) == (BD_NB_ALIVE | BD_NB_HAS_LAM)
            && active(nb->state)) {
            w[n] = a->p.neighbour_weight[j];
            lam[n] = nb->lam;
            n++;
        }
    }
    uint32_t sat = 0u;
    int32_t pin = a->has_price ? (a->p.pinned ? (INT32_C(1) << BD_LAMBDA_Q) : 0) : 0;
    int32_t xi = bd_xi(bd_agent_lambda(a), pin, a->has_price ? a->price : 0, w, lam, n,
                       &sat);
    bd_ctrl_step(&a->ctrl, &a->cs, xi, NULL);
    add(a, BD_C_SATURATIONS, sat, 0u);
}

static void sign(bd_agent *a, bd_frame *f, uint64_t fv)
{
    if (bd_sign_frame(a->own_key, f->id, f->data, fv) != 0) {
        a->fatal = BD_ERR_CRYPTO;
    }
}

static void frame_init(bd_frame *f, uint32_t id)
{
    memset(f, 0, sizeof *f);
    f->id = id;
    f->len = 8u;
}

/* AUTH-13..15: the syncs due at t. */
static size_t syncs(bd_agent *a, int64_t t, bd_frame *out)
{
    if (a->join_until == INT64_MAX) {
        a->join_until = t + a->p.join_ns;   /* the first syncs are the node's hello */
    }
    int due = a->sync_pending || t >= a->sync_next;
    if (a->hello_due && t >= a->hello_after) {
        due = 1;
    }
    if (!due) {
        return 0u;
    }
    a->hello_due = 0;
    a->hello_after = t + a->p.hello_ns;
    a->sync_next = t + a->p.sync_ns;
    a->sync_pending = 0;
    for (int k = 0; k < N_SECURED_TX; ++k) {
        bd_echo *e = &a->echo[ECHO_MC_SYNC + k];
        frame_init(&out[k], e->id);
        bd_encode_sync(a->tx_count[k], a->boot, out[k].data);
        sign(a, &out[k], fv_join(a->boot, a->tx_count[k]));
        remember(e, out[k].data);
    }
    return (size_t)N_SECURED_TX;
}

/* TX-1..4: the next count of a secured frame (a wrap starts a new boot, AUTH-5). */
static int next_count(bd_agent *a, int k, uint32_t *count)
{
    if (a->tx_count[k] > COUNT_MAX) {
        int err = new_boot(a);
        if (err != BD_OK) {
            a->fatal = err;
            return -1;
        }
        for (int j = 0; j < N_SECURED_TX; ++j) {
            a->tx_count[j] = 0u;
        }
        a->sync_pending = 1;
    }
    *count = a->tx_count[k]++;
    return 0;
}

static uint32_t sat_u(uint64_t v, uint32_t max)
{
    return v > max ? max : (uint32_t)v;
}

/* SP-1: ((lam * G + 2^39) >> 40) - O exactly, for any int64 G (a 96-bit product). */
static int64_t setpoint_raw(int32_t lam, int64_t g, int64_t o)
{
    int64_t gh = g >> 32;                          /* floor */
    int64_t gl = (int64_t)((uint64_t)g & 0xFFFFFFFFu);
    int64_t hi = (int64_t)lam * gh;                /* |.| < 2^62 */
    int64_t lo = (int64_t)lam * gl;                /* |.| < 2^63 */
    int64_t c = hi + (lo >> 32);                   /* the product = c * 2^32 + r */
    int64_t r = (int64_t)((uint64_t)lo & 0xFFFFFFFFu) + (INT64_C(1) << 39);  /* < 2^40 */
    int64_t ch = c >> 8;                           /* c = ch * 2^8 + cl */
    int64_t cl = (int64_t)((uint64_t)c & 0xFFu);
    return ch + ((cl << 32) + r) / (INT64_C(1) << 40) - o;
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
    case BD_DIAG_SIG_REJECTEDCRC: return c[BD_C_CRC];
    case BD_DIAG_SIG_REJECTEDDLC: return c[BD_C_DLC];
    case BD_DIAG_SIG_REJECTEDRANGE: return c[BD_C_RANGE];
    case BD_DIAG_SIG_REJECTEDUNKNOWNID: return c[BD_C_UNKNOWN_ID];
    case BD_DIAG_SIG_REJECTEDIMPERSONATION: return c[BD_C_IMPERSONATION];
    case BD_DIAG_SIG_REPEATEDCOUNTER: return c[BD_C_REPEATED_COUNTER];
    case BD_DIAG_SIG_LOSTFRAMES: return c[BD_C_LOST_FRAMES];
    case BD_DIAG_SIG_SATURATIONS: return (uint64_t)c[BD_C_SATURATIONS] + a->cs.saturations;
    case BD_DIAG_SIG_NEIGHBOURTIMEOUTS: return c[BD_C_NEIGHBOUR_TIMEOUTS];
    case BD_DIAG_SIG_PRICETIMEOUTS: return c[BD_C_PRICE_TIMEOUTS];
    case BD_DIAG_SIG_STATUSTIMEOUTS: return c[BD_C_STATUS_TIMEOUTS];
    case BD_DIAG_SIG_PLANTFAULTS: return c[BD_C_PLANT_FAULTS];
    case BD_DIAG_SIG_FOREIGNFRAMES: return c[BD_C_FOREIGN];
    case BD_DIAG_SIG_FOREIGNIDS: return c[BD_C_FOREIGN_ID];
    case BD_DIAG_SIG_INTERLEAVEDCOUNTERS:
        return (uint64_t)c[BD_C_COUNTER_JUMP] + c[BD_C_COUNTER_CLASH];
    case BD_DIAG_SIG_UNTRUSTED: return c[BD_C_UNTRUSTED_SOURCES];
    case BD_DIAG_SIG_IMPLAUSIBLEPRICE: return c[BD_C_IMPLAUSIBLE_PRICE];
    case BD_DIAG_SIG_IMPLAUSIBLELAMBDA: return c[BD_C_IMPLAUSIBLE_LAMBDA];
    case BD_DIAG_SIG_IMPLAUSIBLEGAINS: return c[BD_C_IMPLAUSIBLE_GAINS];
    case BD_DIAG_SIG_SAFETYSENDER: return a->last_safety_sender;
    case BD_DIAG_SIG_SAFETYCAUSE: return a->last_safety_cause;
    case BD_DIAG_SIG_REJECTEDAUTH: return c[BD_C_AUTH];
    case BD_DIAG_SIG_UNSYNCED: return c[BD_C_UNSYNCED];
    case BD_DIAG_SIG_RESYNCS: return c[BD_C_RESYNCS];
    default: return 0u;   /* unreachable: gen_contract.py refuses an unmapped signal */
    }
}

size_t bd_agent_tick(bd_agent *a, int64_t t, bd_frame *out, size_t max)
{
    bd_frame buf[BD_TICK_FRAMES_MAX];
    size_t n;
    uint32_t count;
    if (a->fatal != 0) {
        return 0u;
    }
    a->now = t;
    update_neighbours(a, t);
    update_state(a);
    if (active(a->state)) {
        step(a);
    }
    n = syncs(a, t, buf);
    int32_t lam = bd_agent_lambda(a);
    /* MC every tick (TX-1) */
    if (next_count(a, 0, &count) != 0) {
        return 0u;
    }
    frame_init(&buf[n], a->echo[ECHO_MC].id);
    bd_encode_mc(count % FV_WINDOW, a->state,
                 a->cs.resets % (BD_AGENT_MC_RESETS_MAX + 1u), lam, buf[n].data);
    sign(a, &buf[n], fv_join(a->boot, count));
    remember(&a->echo[ECHO_MC], buf[n].data);
    n++;
    if (a->ticks % BD_SETPOINT_EVERY == 0u) {   /* SP-1..3 */
        int32_t p = 0;
        uint32_t enable = active(a->state) ? 1u : 0u;
        if (enable) {
            int64_t raw = setpoint_raw(lam, a->p.sp_gain, a->p.sp_offset);
            if (raw > a->p.sp_hi || raw < a->p.sp_lo) {
                raw = raw > a->p.sp_hi ? a->p.sp_hi : a->p.sp_lo;
                add(a, BD_C_SETPOINT_LIMITED, 1u, a->echo[ECHO_SETPOINT].id);
            }
            p = (int32_t)raw;
        }
        if (next_count(a, 1, &count) != 0) {
            return 0u;
        }
        frame_init(&buf[n], a->echo[ECHO_SETPOINT].id);
        bd_encode_setpoint(count % FV_WINDOW, enable, p, buf[n].data);
        sign(a, &buf[n], fv_join(a->boot, count));
        remember(&a->echo[ECHO_SETPOINT], buf[n].data);
        n++;
    }
    if (a->ticks % BD_DIAG_EVERY == 0u) {   /* DIAG-1..3 */
        uint32_t v[BD_DIAG_PAGE_SIGNALS_MAX] = {0u};
        uint32_t page = (a->ticks / BD_DIAG_EVERY) % BD_DIAG_PAGES;
        for (uint32_t k = 0u; k < bd_diag_page_signals[page]; ++k) {
            /* counters saturate at their signal's maximum, they never wrap */
            const bd_diag_field *f = &bd_diag_pages[page][k];
            v[k] = sat_u(diag_value(a, f->signal), f->max);
        }
        if (next_count(a, 2, &count) != 0) {
            return 0u;
        }
        frame_init(&buf[n], a->echo[ECHO_DIAG].id);
        bd_encode_diag(count % FV_WINDOW, page, v, buf[n].data);
        sign(a, &buf[n], fv_join(a->boot, count));
        remember(&a->echo[ECHO_DIAG], buf[n].data);
        n++;
    }
    a->ticks++;
    if (a->fatal != 0) {
        return 0u;
    }
    if (n > max) {
        n = max;
    }
    memcpy(out, buf, n * sizeof buf[0]);
    return n;
}

void bd_agent_set_tx_count(bd_agent *a, uint32_t mc, uint32_t setpoint, uint32_t diag)
{
    a->tx_count[0] = mc;
    a->tx_count[1] = setpoint;
    a->tx_count[2] = diag;
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
    for (int k = 0; k < BD_N_SYNC_IDS; ++k) {   /* peers: keys held beyond the inputs' */
        uint32_t sid = bd_sync_ids[k];
        uint32_t sender = sender_of(sid);
        int taken = sender == a->p.id;
        for (uint32_t r = 0u; r < a->n_rx && !taken; ++r) {
            taken = sender_of(a->rx[r].id) == sender;
        }
        int held = 0;
        for (uint32_t q = 0u; q < a->n_listed && !held; ++q) {
            held = a->key_label[q] == sender;
        }
        if (!taken && held && (a->p.fleet_size == 0u || agent_of(sid) <= a->p.fleet_size)) {
            insert_sorted(ids, &n, max, sid);
        }
    }
    return n;
}
