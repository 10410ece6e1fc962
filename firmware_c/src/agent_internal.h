/*
 * What the agent runtime's files share (docs/firmware-spec.md sections 7-14): the
 * freshness layout and its one join and split (AUTH-7), the contract's IDs and keys
 * (AUTH-1), counting (section 10), the state change (section 7), the content rules the
 * receive path applies (section 11) and the Diag page values the tick sends (DIAG-1..3).
 * Defined in src/agent.c, agent_rx.c, agent_rules.c and agent_diag.c; internal to the
 * runtime, not part of include/bessded.
 */
#ifndef BESSDED_AGENT_INTERNAL_H
#define BESSDED_AGENT_INTERNAL_H

#include <stdint.h>

#include "bessded/agent.h"
#include "frames.h"

#define FV_WINDOW (1u << BD_FV_TX_BITS)
#define FV_MAX ((UINT64_C(1) << (BD_FV_BOOT_BITS + BD_FV_COUNT_BITS)) - 1u)
#define FV_COUNT_MASK ((UINT64_C(1) << BD_FV_COUNT_BITS) - 1u)

/* AUTH-7: the one join and split of a freshness value, Boot ‖ Count (the DBC's sizes);
 * inline, as the one-file runtime had them. */
static inline uint64_t fv_join(uint32_t boot, uint32_t count)
{
    return ((uint64_t)boot << BD_FV_COUNT_BITS) | count;
}

static inline uint32_t fv_boot(uint64_t fv)
{
    return (uint32_t)(fv >> BD_FV_COUNT_BITS);
}

/* AUTH-34: λ and its sync carry a tag per receiver (a CAN FD bus with the tags) */
static inline int lambda_tagged(const bd_agent_params *p)
{
    return p->fd != 0u && p->no_lambda_tags == 0u;
}

static inline int active(uint32_t state)
{
    return state == BD_STATE_RUNNING;
}

/* agent_diag.c: add n to counter c (saturating) and report it to on_event */
void bd_count_add(bd_agent *a, int c, uint32_t n, uint32_t frame_id);
/* agent_diag.c: the values of Diag page `page`, each saturated at its signal's maximum */
void bd_diag_page(const bd_agent *a, uint32_t page, uint32_t *v);

/* agent.c: a new state, reported to on_event */
void bd_set_state(bd_agent *a, uint32_t state);
/* agent.c: the agent a per-agent ID belongs to, 0 for the router's */
uint32_t bd_id_agent(uint32_t id);
/* agent.c: the key label code of an ID's DBC sender: 1..32 an agent, plant, router */
uint32_t bd_id_sender(uint32_t id);
/* agent.c: the length of frame `id` on the agent's bus (AUTH-34: an MC or its sync on
 * CAN FD carries the tag slots) */
uint8_t bd_frame_len(const bd_agent *a, uint32_t id);
/* agent.c: a key label code's node label ("agent_3", "plant", "router") */
void bd_label_text(uint32_t code, char out[BD_LABEL_MAX + 1]);
/* agent.c: the index of label's key in a->key (derived in insecure mode); -1 if none */
int bd_key_of(bd_agent *a, uint32_t label);

/* agent_rules.c: an authentic input's content; -1 if out of range (cause `range`) */
int bd_on_price(bd_agent *a, const bd_price_msg *m, uint32_t id, int64_t t);
int bd_on_mc(bd_agent *a, uint32_t j, const bd_mc_msg *m, uint32_t id, int64_t t);
int bd_on_command(bd_agent *a, const bd_command_msg *m, uint32_t id);
void bd_on_status(bd_agent *a, const bd_status_msg *m, uint32_t id, int64_t t);

#if BD_SIGNED_PRICE
/* agent_sig.c (AUTH-31..33): one ER_PriceSig page (AUTH-32: reassembled, the signature
 * verified once per transfer), and whether a decoded ER_Price is the signed segment's
 * (AUTH-33) */
void bd_sig_page(bd_agent *a, const bd_frame *f);
int bd_sig_price_ok(const bd_agent *a, const bd_price_msg *m);
/* AUTH-33, AUTH-35: 1 if the signed segment held is of `boot` or later (a held advance
 * of the router's price to that boot may be taken) */
int bd_sig_vouches(const bd_agent *a, uint32_t boot);
#endif

#endif /* BESSDED_AGENT_INTERNAL_H */
