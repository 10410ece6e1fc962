/*
 * The receive path (docs/firmware-spec.md section 10, section 12.3-12.5): the frame
 * checks in the spec's order (RX-1..13), echo and impersonation, foreign traffic, the
 * failure streaks and untrusted sources, SecOC freshness and the MAC window search
 * (AUTH-9..12, AUTH-25), input and peer syncs (AUTH-13..19, AUTH-21) and the join window
 * (AUTH-26); an authentic input goes to its content rule (agent_rules.c).
 */
#include "bessded/agent.h"

#include <string.h>

#include "agent_internal.h"

#define LOST_WINDOWS 8u     /* windows tried after a sender timed out (AUTH-10) */
#define STALE_WINDOWS 1u    /* past windows tried before a frame is forged (AUTH-25) */
#define SYNC_BOOT_JUMP_MAX 8u  /* boots a sync may move its sender ahead (AUTH-27) */

/* ------------------------------------------------------------------ the contract's IDs */

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

/* ------------------------------------------------------------------ rejections */

static void reject(bd_agent *a, int cause, uint32_t id)
{
    bd_count_add(a, cause, 1u, id);
}

static void foreign(bd_agent *a, int cause, uint32_t id)
{
    bd_count_add(a, BD_C_FOREIGN, 1u, id);
    reject(a, cause, id);
}

/* RX-13: a receive failure (dlc, range, auth: each adds to the streak) on `id`, an
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
        bd_count_add(a, BD_C_UNTRUSTED_SOURCES, 1u, id);
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
    if (f->len != e->len) {
        return 0;
    }
    for (uint32_t k = 0u; k < e->n; ++k) {
        if (memcmp(e->data[k], f->data, e->len) == 0) {
            return 1;
        }
    }
    return 0;
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

/* AUTH-34: the tag of the first slot addressed to this agent in an FD MC or MC sync
 * (f->len checked), NULL if none; a classic frame's is its Mac (bytes 0..2). */
static const uint8_t *tag_of(const bd_agent *a, const bd_frame *f)
{
    if (f->len == 8u) {
        return f->data;
    }
    for (uint32_t k = 0u; k < BD_TAG_SLOTS; ++k) {
        const uint8_t *slot = &f->data[BD_TAG_SLOT_BYTE + k * BD_TAG_SLOT_BYTES];
        if (slot[0] == a->p.id) {
            return &slot[1];
        }
    }
    return NULL;
}

/* 1 if the frame's MAC (its tag to this agent, AUTH-34) verifies under key; none does
 * not; a failed primitive stops the agent. */
static int verifies(bd_agent *a, const uint8_t *key, const bd_frame *f, uint64_t fv)
{
    const uint8_t *tag = tag_of(a, f);
    int v = tag != NULL ? bd_tag_verifies(key, f->id, f->data, fv, tag) : 0;
    if (v < 0) {
        a->fatal = BD_ERR_CRYPTO;
    }
    return v == 1;
}

/* The key a slot's frames (and its sync) verify with: AUTH-30, the command slot's is
 * the agent's command key (its sync keeps the router's node key: sync = 1); AUTH-34, a
 * neighbour's MC on CAN FD the key of its tags to this agent; the others' their sender's
 * or link frame's. */
static const uint8_t *frame_key(const bd_agent *a, const bd_rx_slot *s, int sync)
{
    uint32_t r = (uint32_t)(s - a->rx);
    if (r >= BD_RX_MC0 && lambda_tagged(&a->p)) {
        return a->tag_rx_key[r - BD_RX_MC0];
    }
    return s == &a->rx[BD_RX_COMMAND] && !sync ? a->command_key : a->key[s->key_index];
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
        if (!seen(s, fv) && verifies(a, frame_key(a, s, 0), f, fv)) {
            s->seen = (uint16_t)(s->seen | (1u << (s->fv - fv)));   /* again: a replay */
            return 1;
        }
        if (fv < FV_WINDOW) {
            break;
        }
    }
    return 0;
}

/* AUTH-27: take a boot advance to v (a sync's FV - 1); the undo point first, unless a
 * second advance has had no frame since the first (forged syncs in a row are undone
 * together). */
static void take_advance(bd_agent *a, bd_rx_slot *s, uint64_t v, uint32_t id)
{
    if ((s->flags & BD_RX_SPOKE) != 0u || (s->flags & BD_RX_BACK) == 0u) {
        s->back_boot = (uint16_t)fv_boot(s->fv);
        s->back_count = (uint32_t)(s->fv & FV_COUNT_MASK);
        s->flags |= BD_RX_BACK;
    }
    s->flags &= (uint8_t)~(BD_RX_SPOKE | BD_RX_LOST);
    s->seen = 0u;   /* a later boot: no value of it accepted yet */
    s->fv = v;
    bd_count_add(a, BD_C_RESYNCS, 1u, id);
    a->hello_due = 1;   /* a peer restarted: tell it our freshness now */
}

/* AUTH-11..13: 1 if the frame verifies at a FV from the candidate after `base` on, one
 * per window, `windows` windows forward (*fv: that FV). */
static int search(bd_agent *a, const bd_rx_slot *s, const bd_frame *f, uint64_t base,
                  uint32_t counter, uint32_t windows, uint64_t *fv)
{
    if (bd_fv_candidate(base, counter, BD_FV_TX_BITS, FV_MAX, fv) != 0) {
        return 0;
    }
    for (; windows > 0u; --windows, *fv += FV_WINDOW) {
        if (verifies(a, frame_key(a, s, 0), f, *fv)) {
            return 1;
        }
    }
    return 0;
}

/* AUTH-35: a verified sync of `boot`, below the boot of the advance the input holds (the
 * boot it is in, or a later one its sender restarted to): a sender never goes back, so
 * the held advance was forged: dropped, `sync_jump`. */
static void drop_pending(bd_agent *a, bd_rx_slot *s, uint32_t boot, uint32_t id)
{
    if ((s->flags & BD_RX_PENDING) != 0u && fv_boot(s->pending + 1u) > boot) {
        s->flags &= (uint8_t)~BD_RX_PENDING;
        bd_count_add(a, BD_C_SYNC_JUMP, 1u, id);
    }
}

/* AUTH-9..12: 1 if a decoded secured frame is authentic and fresh (and accepted). */
static int authentic(bd_agent *a, bd_rx_slot *s, const bd_frame *f, uint32_t counter,
                     int64_t t)
{
    if ((s->flags & BD_RX_HAS_FV) == 0u) {
        reject(a, a->joining ? BD_C_JOINING : BD_C_UNSYNCED, f->id);
        return 0;
    }
    /* AUTH-30: commands to other agents move the router's count unseen: the wide search
     * for every command */
    int command = s == &a->rx[BD_RX_COMMAND];
    uint32_t windows = ((s->flags & BD_RX_LOST) != 0u || command) ? LOST_WINDOWS : 1u;
    uint64_t fv;
    int found = search(a, s, f, s->fv, counter, windows, &fv);
    if (!found && (s->flags & BD_RX_PENDING) != 0u
        && search(a, s, f, s->pending, counter, windows, &fv)) {
        /* AUTH-35: it verifies on the held boot advance: its sender did restart */
#if BD_SIGNED_PRICE
        if (s == &a->rx[BD_RX_PRICE] && a->p.signed_price != 0u
            && !bd_sig_vouches(a, fv_boot(fv))) {
            /* AUTH-33: no price signature of that boot yet: held, not taken */
            reject(a, BD_C_UNSYNCED, f->id);
            return 0;
        }
#endif
        s->flags &= (uint8_t)~BD_RX_PENDING;
        take_advance(a, s, s->pending, s->sync_id);
        found = 1;
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
    s->flags |= BD_RX_SPOKE;   /* AUTH-27: a frame since the latest boot advance */
    uint64_t gap = command ? 0u : fv - last - 1u;   /* AUTH-30: others' commands, not lost */
    bd_count_add(a, BD_C_LOST_FRAMES, gap > UINT32_MAX ? UINT32_MAX : (uint32_t)gap, f->id);
    return 1;
}

/* AUTH-16, AUTH-26: a verified sync of value v below `last`, the last one accepted:
 * less than one window behind, its tick's frame overtook it (`stale`, no streak);
 * further, a replay (`auth`). */
static void old_sync(bd_agent *a, uint64_t last, uint64_t v, uint32_t id, int64_t t)
{
    if (last - v < FV_WINDOW) {
        reject(a, BD_C_STALE, id);
    } else {
        fail(a, NULL, id, BD_C_AUTH, t);
    }
}

/* AUTH-27: a verified sync of value v below the last one, of a boot below the current
 * one but not below the one its sender left at its latest boot advance, and newer than
 * anything taken of that boot: the sender is alive where the advance said it was not,
 * so the advance was forged. Taken (1); else 0, nothing done. */
static int revert(bd_agent *a, bd_rx_slot *s, uint64_t v, uint32_t boot, uint32_t id)
{
    uint64_t back = fv_join(s->back_boot, s->back_count);
    if ((s->flags & BD_RX_BACK) == 0u || v == 0u || v - 1u <= back
        || boot >= fv_boot(s->fv + 1u) || boot < fv_boot(back + 1u)) {
        return 0;
    }
    drop_pending(a, s, boot, id);
    s->flags &= (uint8_t)~(BD_RX_BACK | BD_RX_LOST);
    s->seen = seen_after(s, 0, v - 1u, 0u);
    s->fv = v - 1u;
    bd_count_add(a, BD_C_RESYNCS, 1u, id);
    bd_count_add(a, BD_C_SYNC_JUMP, 1u, id);
    a->hello_due = 1;
    return 1;
}

/* AUTH-13..17: a sync of one of the agent's inputs. */
static void on_sync(bd_agent *a, bd_rx_slot *s, const bd_frame *f, int64_t t)
{
    bd_sync_msg m;
    if (f->len != bd_frame_len(a, f->id)) {
        fail(a, NULL, f->id, BD_C_DLC, t);
        return;
    }
    if (bd_decode_sync(f->data, &m) != 0) {
        fail(a, NULL, f->id, BD_C_RANGE, t);
        return;
    }
    uint64_t fv = fv_join(m.boot, m.count);
    if (!verifies(a, frame_key(a, s, 1), f, fv)
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
            old_sync(a, s->fv, fv, f->id, t);   /* older than one already heard */
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
            drop_pending(a, s, m.boot, f->id);
            return;
        }
        if (!a->insecure) {   /* a genuine sync never goes back */
            if (!revert(a, s, fv, m.boot, f->id)) {
                old_sync(a, s->fv, fv - 1u, f->id, t);
            }
            return;
        }
        s->flags &= (uint8_t)~BD_RX_HAS_FV;   /* --insecure: a restarted sender is at boot 1 */
        restarted = 1;
    } else if (has_fv && !a->insecure) {
        uint32_t expected = fv_boot(s->fv + 1u);
        uint64_t reach = (s == &a->rx[BD_RX_COMMAND] ? LOST_WINDOWS : 1u) * FV_WINDOW;
        /* AUTH-27: a genuine sender never jumps that far (a forged sync must not lock it
         * out for good), nor further in its boot than a frame of an input in step could
         * move it (a receiver that missed more of a live sender has timed it out) */
        if (m.boot > expected + SYNC_BOOT_JUMP_MAX
            || (m.boot == expected && (s->flags & BD_RX_LOST) == 0u
                && fv - 1u - s->fv > reach)) {
            bd_count_add(a, BD_C_SYNC_JUMP, 1u, f->id);
            fail(a, NULL, f->id, BD_C_AUTH, t);
            return;
        }
        if (m.boot > expected) {
            if ((s->flags & BD_RX_LOST) == 0u) {
                /* AUTH-35: an input in step holds it until a frame verifies on it */
                drop_pending(a, s, m.boot, f->id);   /* one of a later boot: forged */
                s->pending = fv - 1u;
                s->flags |= BD_RX_PENDING;
                return;
            }
            take_advance(a, s, fv - 1u, f->id);
            return;
        }
        drop_pending(a, s, m.boot, f->id);
    }
    if (fv - 1u <= FV_MAX) {
        s->seen = seen_after(s, (s->flags & BD_RX_HAS_FV) != 0u, fv - 1u, 0u);
        s->fv = fv - 1u;
        s->flags |= BD_RX_HAS_FV;
    }
    s->flags &= (uint8_t)~BD_RX_LOST;
    bd_count_add(a, BD_C_RESYNCS, 1u, f->id);
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
        bd_count_add(a, BD_C_RESYNCS, 1u, s->sync_id);
    }
}

/* AUTH-19: a sync of a frame the agent does not use, from a node whose key it holds:
 * verified only to notice a peer's (re)start. 1 if it was such a sync. */
static int peer_sync(bd_agent *a, const bd_frame *f, int64_t t, int k)
{
    if (a->p.fleet_size != 0u && bd_id_agent(f->id) > a->p.fleet_size) {
        return 0;
    }
    if ((f->id > BD_SETPOINT_SYNC_BASE && f->id <= BD_SETPOINT_SYNC_BASE + BD_N_AGENTS_MAX)
        || (f->id > BD_STATUS_SYNC_BASE && f->id <= BD_STATUS_SYNC_BASE + BD_N_AGENTS_MAX)) {
        return 0;   /* AUTH-28: another agent's link frame, under a key it does not hold */
    }
    uint32_t label = bd_id_sender(f->id);
    /* AUTH-34: another agent's MC sync on CAN FD verifies under the key of its tags to
     * this agent: its peer only if it has a slot for it and the key is held (derived in a
     * simulated fleet; a key file holds its neighbours' only, whose syncs are inputs) */
    int tagged = bd_frame_len(a, f->id) != 8u;
    if (tagged && (!a->derive || f->len != BD_FD_MC_BYTES || tag_of(a, f) == NULL)) {
        return 0;
    }
    int key = (label == a->p.id) ? -2 : bd_key_of(a, label);   /* and its floor */
    if (key == -1) {
        return 0;
    }
    bd_sync_msg m;
    if (f->len != bd_frame_len(a, f->id) || bd_decode_sync(f->data, &m) != 0) {
        return 1;   /* not a usable sync; not this node's input either */
    }
    if (a->peer_boot[k] == m.boot) {
        return 1;
    }
    uint64_t fv = fv_join(m.boot, m.count);
    uint8_t tag_key[BD_KEY_BYTES];
    const uint8_t *kk = a->own_key;
    if (tagged) {
        char from[BD_LABEL_MAX + 1];
        char to[BD_LABEL_MAX + 1];
        bd_label_text(label, from);
        bd_label_text(a->p.id, to);
        if (bd_derive_lambda_tag_key(a->master, from, to, tag_key) != 0) {
            a->fatal = BD_ERR_CRYPTO;
            return 1;
        }
        kk = tag_key;
    } else if (key >= 0) {
        kk = a->key[key];
    }
    if (!verifies(a, kk, f, fv)
        || (key >= 0 && m.boot < a->key_floor[key])) {   /* AUTH-21 */
        fail(a, NULL, f->id, BD_C_AUTH, t);
        return 1;
    }
    a->peer_boot[k] = (uint16_t)m.boot;
    a->hello_due = 1;
    return 1;
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
        if (bad == 0 && cm.target != a->p.id) {
            return 0;   /* AUTH-30: a command to another agent, under a key it lacks: not for it */
        }
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
#if BD_SIGNED_PRICE
    if (r == BD_RX_PRICE && a->p.signed_price != 0u && !bd_sig_price_ok(a, &pm)) {
        /* AUTH-33: not the signed segment's price, refused before its MAC and freshness
         * (it cannot move the router's counter ahead of its genuine frames) */
        reject(a, BD_C_UNSIGNED_PRICE, f->id);
        return 0;
    }
#endif
    if (!authentic(a, s, f, counter, t)) {
        return 0;
    }
    uint32_t before = a->safety_rejections;
    int err;
    switch (r) {
    case BD_RX_PRICE:
        err = bd_on_price(a, &pm, f->id, t);
        break;
    case BD_RX_COMMAND:
        err = bd_on_command(a, &cm, f->id);
        break;
    case BD_RX_STATUS:
        bd_on_status(a, &sm, f->id, t);
        err = 0;
        break;
    default:
        err = bd_on_mc(a, r - BD_RX_MC0, &mm, f->id, t);
        break;
    }
    if (err != 0) {
        fail(a, s, f->id, BD_C_RANGE, t);
        return 0;
    }
    if (a->safety_rejections == before) {
        s->streak = 0u;   /* valid and plausible: the failure streak is over */
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
    /* RX-2: remote, error, or a data frame of the other format than the bus's (GEN-1) */
    if ((f->flags & (BD_FRAME_RTR | BD_FRAME_ERR)) != 0u
        || ((f->flags & BD_FRAME_FD) != 0u) != (a->p.fd != 0u)) {
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
#if BD_SIGNED_PRICE
    if (id == BD_ER_PRICESIG_ID && a->p.signed_price != 0u) {
        bd_sig_page(a, f);   /* AUTH-32: no MAC of its own, the signature is checked */
        return;
    }
#endif
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
        } else if (a->p.fleet_size != 0u && bd_id_agent(id) > a->p.fleet_size) {
            foreign(a, BD_C_FOREIGN_ID, id);
        }
        return;   /* a DBC frame that is not for this node */
    }
    if ((s->flags & BD_RX_UNTRUSTED) != 0u && t >= s->untrusted_until) {
        s->flags &= (uint8_t)~BD_RX_UNTRUSTED;   /* inputs are secured: frames prove themselves */
    }
    if (f->len != bd_frame_len(a, id)) {   /* AUTH-34: an FD MC is 32 bytes */
        fail(a, s, id, BD_C_DLC, t);
        return;
    }
    (void)decode_and_use(a, s, f, t);
}
