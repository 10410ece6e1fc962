/*
 * The agent runtime's start and its own side (include/bessded/agent.h): the contract's
 * IDs and the sender keys (AUTH-1), init and the boot counter (sections 3, 4, AUTH-3),
 * liveness and timeouts (section 8), the state machine (section 7), the controller step,
 * and the tick with the frames it signs and sends (section 9, AUTH-4..5, AUTH-13..15).
 * The receive path is in agent_rx.c, the content rules in agent_rules.c, the counters and
 * Diag values in agent_diag.c. Port of firmware_py/runtime.py and nodeio.py; integers
 * only, times are int64 ns.
 */
#include "bessded/agent.h"

#include <string.h>

#include "agent_internal.h"

#define LABEL_PLANT (BD_N_AGENTS_MAX + 1u)
#define LABEL_ROUTER (BD_N_AGENTS_MAX + 2u)
#define COUNT_MAX ((1u << BD_FV_COUNT_BITS) - 1u)
#define BOOT_MAX ((1u << BD_FV_BOOT_BITS) - 1u)
#define INSECURE_BOOT 1u
#define ECHO_MC 0
#define ECHO_SETPOINT 1
#define ECHO_DIAG 2
#define ECHO_MC_SYNC 3
#define ECHO_SETPOINT_SYNC 4
#define ECHO_DIAG_SYNC 5
#define N_SECURED_TX 3          /* own secured IDs: MC, Setpoint, Diag (tx_count index) */

/* ------------------------------------------------------------------ the contract's IDs */

static int in_block(uint32_t id, uint32_t base)
{
    return id > base && id <= base + BD_N_AGENTS_MAX;
}

/* The agent a per-agent ID belongs to (AGENT_<i>_*, PLANT_<i>_*), 0 for the router's. */
uint32_t bd_id_agent(uint32_t id)
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
uint32_t bd_id_sender(uint32_t id)
{
    if (in_block(id, BD_STATUS_BASE) || in_block(id, BD_STATUS_SYNC_BASE)) {
        return LABEL_PLANT;
    }
    uint32_t i = bd_id_agent(id);
    return i != 0u ? i : LABEL_ROUTER;
}

uint8_t bd_frame_len(const bd_agent *a, uint32_t id)
{
    int mc = in_block(id, BD_MC_BASE) || in_block(id, BD_MC_SYNC_BASE);
    return (uint8_t)(lambda_tagged(&a->p) && mc ? BD_FD_MC_BYTES : 8u);
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

void bd_label_text(uint32_t code, char out[BD_LABEL_MAX + 1])
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
int bd_key_of(bd_agent *a, uint32_t label)
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
    bd_label_text(label, text);
    if (bd_derive_node_key(a->master, text, a->key[a->n_keys]) != 0) {
        a->fatal = BD_ERR_CRYPTO;
        return -1;
    }
    a->key_label[a->n_keys] = (uint8_t)label;
    return (int)a->n_keys++;
}

/* AUTH-28: a link frame's name, prefix || id (1..32, decimal) || suffix */
static void frame_name(const char *prefix, uint32_t id, const char *suffix,
                       char out[BD_LABEL_MAX + 1])
{
    size_t n = strlen(prefix);
    memcpy(out, prefix, n);
    if (id >= 10u) {
        out[n++] = (char)('0' + id / 10u);
    }
    out[n++] = (char)('0' + id % 10u);
    memcpy(&out[n], suffix, strlen(suffix) + 1u);
}

/* AUTH-34: a TagRx code's node label ("agent_3", "plant", "router") */
static void tag_label(uint32_t code, char out[BD_LABEL_MAX + 1])
{
    bd_label_text(code == BD_TAG_RX_PLANT ? LABEL_PLANT : code == BD_TAG_RX_ROUTER ? LABEL_ROUTER
               : code, out);
}

/* AUTH-34: K_tag(sender -> receiver) (TagRx codes), derived or from the keyring; -1 if
 * the keyring does not hold it (its index in keys->tag_* in *at, -1 if derived) */
static int pair_key(const bd_agent *a, const bd_keyring *keys, uint32_t sender,
                    uint32_t receiver, uint8_t out[BD_KEY_BYTES], int *at)
{
    *at = -1;
    if (a->derive) {
        char from[BD_LABEL_MAX + 1];
        char to[BD_LABEL_MAX + 1];
        tag_label(sender, from);
        tag_label(receiver, to);
        return bd_derive_lambda_tag_key(a->master, from, to, out) != 0 ? BD_ERR_CRYPTO : BD_OK;
    }
    for (uint32_t k = 0u; k < keys->n_tags && k < BD_TAG_KEYS_MAX; ++k) {
        if (keys->tag_pair[k][0] == sender && keys->tag_pair[k][1] == receiver) {
            memcpy(out, keys->tag_key[k], BD_KEY_BYTES);
            *at = (int)k;
            return BD_OK;
        }
    }
    return BD_ERR_MISSING_KEY;
}

/* AUTH-34 (CAN FD): the receivers of its λ tags, its neighbours by ascending index, then
 * the plant and the router, with their keys; the keys of its neighbours' tags to it */
static int init_tags(bd_agent *a, const bd_keyring *keys)
{
    uint32_t n = 0u;
    int at;
    for (uint32_t id = 1u; id <= BD_N_AGENTS_MAX; ++id) {
        for (uint32_t j = 0u; j < a->p.n_neighbours; ++j) {
            if (a->p.neighbour_id[j] == id && n < BD_FD_NEIGHBOURS_MAX) {
                a->tag_code[n++] = (uint8_t)id;
                break;
            }
        }
    }
    a->tag_code[n++] = BD_TAG_RX_PLANT;
    a->tag_code[n++] = BD_TAG_RX_ROUTER;
    for (uint32_t k = 0u; k < n; ++k) {
        int err = pair_key(a, keys, a->p.id, a->tag_code[k], a->tag_key[k], &at);
        if (err != BD_OK) {
            return err;
        }
    }
    for (uint32_t j = 0u; j < a->p.n_neighbours; ++j) {
        uint32_t nb = a->p.neighbour_id[j];
        int err = pair_key(a, keys, nb, a->p.id, a->tag_rx_key[j], &at);
        if (err != BD_OK) {
            return err;
        }
        /* its frames need no node key of the neighbour: a key table entry that verifies
         * nothing holds its boot floor (AUTH-21) */
        if (!a->derive && bd_key_of(a, nb) < 0) {
            if (a->n_keys >= BD_MAX_PEERS) {
                return BD_ERR_PARAMS;
            }
            a->key_label[a->n_keys] = (uint8_t)nb;
            a->key_floor[a->n_keys] = a->insecure || at < 0 ? 0u : keys->tag_floor[at];
            memset(a->key[a->n_keys], 0, BD_KEY_BYTES);
            a->n_keys++;
        }
    }
    return BD_OK;
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

static void init_echo(bd_agent *a, bd_echo *e, uint32_t id)
{
    memset(e, 0, sizeof *e);
    e->id = (uint16_t)id;
    e->len = bd_frame_len(a, id);
}

int bd_agent_init(bd_agent *a, const bd_agent_params *p, const bd_keyring *keys,
                  bd_event_fn on_event, void *event_ctx)
{
    memset(a, 0, sizeof *a);
    if (p->id < 1u || p->id > BD_N_AGENTS_MAX || p->n_neighbours > BD_MAX_NEIGHBOURS
        || p->fleet_size > BD_N_AGENTS_MAX || p->period_ns <= 0
        || bd_ctrl_config_check(&p->ctrl) != BD_OK || keys->n_peers > BD_MAX_PEERS
        || (lambda_tagged(p) && p->n_neighbours > BD_FD_NEIGHBOURS_MAX)) {   /* AUTH-34 */
        return BD_ERR_PARAMS;
    }
    a->p = *p;
    a->ctrl = p->ctrl;
    a->pinned = p->pinned != 0 ? 1 : 0;
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
    /* AUTH-28: the link frame keys; PLANT_<id>_Status's takes the plant's place in the
     * key table (the agent takes nothing else from the plant) */
    uint8_t status_key[BD_KEY_BYTES];
    uint16_t status_floor = a->insecure ? 0u : keys->status_floor;
    if (a->derive) {
        char name[BD_LABEL_MAX + 1];
        frame_name("AGENT_", p->id, "_Setpoint", name);
        int bad = bd_derive_frame_key(a->master, name, a->setpoint_key);
        frame_name("AGENT_", p->id, "_Diag", name);
        bad |= bd_derive_frame_key(a->master, name, a->diag_key);
        frame_name("agent_", p->id, "", name);   /* AUTH-30: the commands' target */
        bad |= bd_derive_command_key(a->master, name, a->command_key);
        frame_name("PLANT_", p->id, "_Status", name);
        if (bad != 0 || bd_derive_frame_key(a->master, name, status_key) != 0) {
            return BD_ERR_CRYPTO;
        }
    } else if (keys->has_frame_keys) {
        memcpy(a->setpoint_key, keys->setpoint_key, BD_KEY_BYTES);
        memcpy(a->diag_key, keys->diag_key, BD_KEY_BYTES);
        memcpy(a->command_key, keys->command_key, BD_KEY_BYTES);
        memcpy(status_key, keys->status_key, BD_KEY_BYTES);
    } else {
        return BD_ERR_MISSING_KEY;
    }
    uint32_t plant = 0u;
    while (plant < a->n_keys && a->key_label[plant] != LABEL_PLANT) {
        plant++;
    }
    if (plant == a->n_keys) {
        if (a->n_keys >= BD_MAX_PEERS) {
            return BD_ERR_PARAMS;
        }
        a->key_label[plant] = LABEL_PLANT;
        a->key_floor[plant] = 0u;
        a->n_keys++;
    }
    memcpy(a->key[plant], status_key, BD_KEY_BYTES);
    if (status_floor > a->key_floor[plant]) {
        a->key_floor[plant] = status_floor;
    }
    if (lambda_tagged(p)) {
        int err = init_tags(a, keys);
        if (err != BD_OK) {
            return err;
        }
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
        int k = bd_key_of(a, bd_id_sender(ids[r]));
        if (k < 0) {
            return a->fatal != 0 ? a->fatal : BD_ERR_MISSING_KEY;
        }
        s->key_index = (uint8_t)k;
        if (a->insecure) {  /* every insecure sender runs at boot 1 from count 0 */
            s->flags = BD_RX_HAS_FV | BD_RX_LOST;
            s->fv = fv_join(INSECURE_BOOT, 0u) - 1u;
        }
    }
    if (p->signed_price != 0u) {   /* AUTH-31: the router's public key verifies its price */
#if BD_SIGNED_PRICE
        if (!keys->has_price_key) {
            return BD_ERR_PRICE_KEY;
        }
        memcpy(a->sig.key, keys->price_key, sizeof a->sig.key);
        memcpy(a->sig.fleet, keys->fleet_id, sizeof a->sig.fleet);
#else
        return BD_ERR_PRICE_KEY;   /* built without the signed price */
#endif
    }
    /* the peer syncs the acceptance filter passes: keys held beyond the inputs' senders */
    a->n_listed = a->derive ? 0u : a->n_keys;
    init_echo(a, &a->echo[ECHO_MC], BD_MC_BASE + p->id);
    init_echo(a, &a->echo[ECHO_SETPOINT], BD_SETPOINT_BASE + p->id);
    init_echo(a, &a->echo[ECHO_DIAG], BD_DIAG_BASE + p->id);
    init_echo(a, &a->echo[ECHO_MC_SYNC], BD_MC_SYNC_BASE + p->id);
    init_echo(a, &a->echo[ECHO_SETPOINT_SYNC], BD_SETPOINT_SYNC_BASE + p->id);
    init_echo(a, &a->echo[ECHO_DIAG_SYNC], BD_DIAG_SYNC_BASE + p->id);
    a->sync_pending = 1;
    a->hello_after = INT64_MIN;
    a->join_until = INT64_MAX;
    a->joining = !a->insecure && p->join_ns > 0;   /* insecure: every state preset */
    return new_boot(a);   /* AUTH-3: before the first frame is signed */
}

/* ------------------------------------------------------------------ state */

void bd_set_state(bd_agent *a, uint32_t state)
{
    a->state = state;
    if (a->on_event != NULL) {
        a->on_event(a->event_ctx, BD_EV_STATE, 0u, state);
    }
}

/* ------------------------------------------------------------------ periodic */

static void sender_lost(bd_rx_slot *s)
{
    s->flags |= BD_RX_LOST;
    s->flags &= (uint8_t)~BD_RX_PENDING;   /* its next sync is taken as it comes (AUTH-35) */
}

static void update_neighbours(bd_agent *a, int64_t t)
{
    for (uint32_t j = 0u; j < a->p.n_neighbours; ++j) {
        bd_neighbour *n = &a->nb[j];
        int alive = (n->flags & BD_NB_HAS_RX) != 0u && t - n->last_rx <= a->p.neighbour_timeout_ns;
        if ((n->flags & BD_NB_ALIVE) != 0u && !alive) {
            bd_count_add(a, BD_C_NEIGHBOUR_TIMEOUTS, 1u, a->rx[BD_RX_MC0 + j].id);
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
        bd_count_add(a, BD_C_PRICE_TIMEOUTS, 1u, BD_ER_PRICE_ID);
        sender_lost(&a->rx[BD_RX_PRICE]);
        sender_lost(&a->rx[BD_RX_COMMAND]);   /* the router's: its command count moved unseen */
    }
    if (a->status_fresh && !status_ok) {
        bd_count_add(a, BD_C_STATUS_TIMEOUTS, 1u, a->rx[BD_RX_STATUS].id);
        sender_lost(&a->rx[BD_RX_STATUS]);
    }
    a->price_fresh = (uint8_t)price_ok;
    a->status_fresh = (uint8_t)status_ok;
    if (a->state == BD_STATE_ISOLATED) {
        return;
    }
    int healthy = price_ok && status_ok && !a->plant_fault;
    if (a->state == BD_STATE_RUNNING && !healthy) {
        bd_set_state(a, BD_STATE_SAFE);
        a->cs.nu = 0;
        a->cs.xi_prev = 0;
    } else if ((a->state == BD_STATE_INIT || a->state == BD_STATE_SAFE) && healthy) {
        bd_set_state(a, BD_STATE_RUNNING);
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
    int32_t pin = a->has_price ? (a->pinned ? (INT32_C(1) << BD_LAMBDA_Q) : 0) : 0;
    n = bd_wmsr_trim(bd_agent_lambda(a), a->p.resilient_f, w, lam, n);  /* WMSR-1 */
    int32_t xi = bd_xi(bd_agent_lambda(a), pin, a->has_price ? a->price : 0, w, lam, n,
                       &sat);
    bd_ctrl_step(&a->ctrl, &a->cs, xi, NULL);
    bd_count_add(a, BD_C_SATURATIONS, sat, 0u);
}

/* ------------------------------------------------------------------ transmit */

static void remember(bd_echo *e, const bd_frame *f)
{
    memcpy(e->data[e->next], f->data, BD_FRAME_DATA);
    e->next = (uint8_t)((e->next + 1u) % BD_ECHO_DEPTH);
    if (e->n < BD_ECHO_DEPTH) {
        e->n++;
    }
}

/* AUTH-34: on CAN FD its MC and MC sync carry, instead of the Mac (0), a tag for each
 * receiver under the pair's key */
static void tag(bd_agent *a, bd_frame *f, uint64_t fv)
{
    f->len = BD_FD_MC_BYTES;
    for (uint32_t k = 0u; k < BD_TAG_SLOTS && a->tag_code[k] != 0u; ++k) {
        uint8_t *slot = &f->data[BD_TAG_SLOT_BYTE + k * BD_TAG_SLOT_BYTES];
        slot[0] = a->tag_code[k];
        if (bd_tag_frame(a->tag_key[k], f->id, f->data, fv, &slot[1]) != 0) {
            a->fatal = BD_ERR_CRYPTO;
        }
    }
}

static void sign(bd_agent *a, bd_frame *f, uint64_t fv)
{
    if (bd_frame_len(a, f->id) != 8u) {
        tag(a, f, fv);
        return;
    }
    /* AUTH-28, AUTH-29: the setpoint and the Diag (and their syncs) under their own keys */
    int link = f->id == BD_SETPOINT_BASE + a->p.id || f->id == BD_SETPOINT_SYNC_BASE + a->p.id;
    int diag = f->id == BD_DIAG_BASE + a->p.id || f->id == BD_DIAG_SYNC_BASE + a->p.id;
    const uint8_t *key = link ? a->setpoint_key : diag ? a->diag_key : a->own_key;
    if (bd_sign_frame(key, f->id, f->data, fv) != 0) {
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
        remember(e, &out[k]);
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

/* TX-7: send the MC frame this tick? Always when periodic; in event mode the first tick,
 * a State change, |lambda - lambda last sent| > threshold, or heartbeat ticks since the
 * last one (its neighbours hold the lambda they last heard until then). */
static int mc_due(bd_agent *a, int32_t lam)
{
    int64_t moved = (int64_t)lam - (int64_t)a->mc_last_lam;
    a->mc_age++;
    if (a->p.tx_event != 0u && a->mc_has_last != 0 && a->mc_age < a->p.tx_heartbeat
        && a->mc_last_state == a->state && (moved < 0 ? -moved : moved) <= a->p.tx_threshold) {
        return 0;
    }
    a->mc_last_lam = lam;
    a->mc_last_state = a->state;
    a->mc_age = 0u;
    a->mc_has_last = 1;
    return 1;
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
    /* MC every tick (TX-1), or when due in event mode (TX-7) */
    if (mc_due(a, lam)) {
        if (next_count(a, 0, &count) != 0) {
            return 0u;
        }
        frame_init(&buf[n], a->echo[ECHO_MC].id);
        bd_encode_mc(count % FV_WINDOW, a->state,
                     a->cs.resets % (BD_AGENT_MC_RESETS_MAX + 1u), lam, buf[n].data);
        sign(a, &buf[n], fv_join(a->boot, count));
        remember(&a->echo[ECHO_MC], &buf[n]);
        n++;
    }
    if (a->ticks % BD_SETPOINT_EVERY == 0u) {   /* SP-1..3 */
        int32_t p = 0;
        uint32_t enable = active(a->state) ? 1u : 0u;
        if (enable) {
            int64_t raw = setpoint_raw(lam, a->p.sp_gain, a->p.sp_offset);
            if (raw > a->p.sp_hi || raw < a->p.sp_lo) {
                raw = raw > a->p.sp_hi ? a->p.sp_hi : a->p.sp_lo;
                bd_count_add(a, BD_C_SETPOINT_LIMITED, 1u, a->echo[ECHO_SETPOINT].id);
            }
            p = (int32_t)raw;
        }
        if (next_count(a, 1, &count) != 0) {
            return 0u;
        }
        frame_init(&buf[n], a->echo[ECHO_SETPOINT].id);
        bd_encode_setpoint(count % FV_WINDOW, enable, p, buf[n].data);
        sign(a, &buf[n], fv_join(a->boot, count));
        remember(&a->echo[ECHO_SETPOINT], &buf[n]);
        n++;
    }
    if (a->ticks % BD_DIAG_EVERY == 0u) {   /* DIAG-1..3 */
        uint32_t v[BD_DIAG_PAGE_SIGNALS_MAX] = {0u};
        uint32_t page = (a->ticks / BD_DIAG_EVERY) % BD_DIAG_PAGES;
        bd_diag_page(a, page, v);
        if (next_count(a, 2, &count) != 0) {
            return 0u;
        }
        frame_init(&buf[n], a->echo[ECHO_DIAG].id);
        bd_encode_diag(count % FV_WINDOW, page, v, buf[n].data);
        sign(a, &buf[n], fv_join(a->boot, count));
        remember(&a->echo[ECHO_DIAG], &buf[n]);
        n++;
    }
    a->ticks++;
    if (a->fatal != 0) {
        return 0u;
    }
    if (n > max) {
        n = max;
    }
    for (size_t k = 0u; k < n; k++) {   /* GEN-1: the bus's one frame format */
        buf[k].flags = a->p.fd != 0u ? (uint8_t)(BD_FRAME_FD | BD_FRAME_BRS) : 0u;
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
