/*
 * The agent runtime (docs/firmware-spec.md sections 7-14): receive checks (DLC, ranges,
 * SecOC freshness and MAC, echo and impersonation, foreign traffic, untrusted sources),
 * the safety rules, liveness and timeouts, the state machine, commands, the controller
 * step and the frames an agent sends. Bit-exact C99 port of firmware_py/runtime.py and
 * firmware_py/nodeio.py.
 *
 * Pure like the controller core: no clock, no bus, no heap, no floating point. The node
 * loop (src/node.c) hands every received frame to bd_agent_rx with its receive time and
 * calls bd_agent_tick once per period; the platform seam (platform.h) does the rest.
 * Times are int64 nanoseconds of a monotonic clock. Every binary64 quantity of the
 * configuration is turned into integers once, before the agent starts (bd_agent_params,
 * filled by src/config.c on a host, or by a build step for an MCU).
 */
#ifndef BESSDED_AGENT_H
#define BESSDED_AGENT_H

#include <stddef.h>
#include <stdint.h>

#include "bd_contract.h"   /* generated from the DBC (firmware_c/gen_contract.py) */
#include "bessded/controller.h"
#include "bessded/frame.h"
#include "bessded/secoc.h"

#ifdef __cplusplus
extern "C" {
#endif

/* The signed price (AUTH-31..33): 1 on a host, where libsodium verifies the router's
 * Ed25519 signatures (src/crypto_sodium.c); 0 compiles it out (the Cortex-M4 image,
 * `make arm-size`: no libsodium there), and bd_agent_init then refuses signed_price. */
#ifndef BD_SIGNED_PRICE
#define BD_SIGNED_PRICE 1
#endif

#define BD_MAX_NEIGHBOURS (BD_N_AGENTS_MAX - 1)
#define BD_RESILIENT_F_MAX ((BD_N_AGENTS_MAX - 1) / 2) /* 2F trimmed leave one (WMSR-1) */
#define BD_MAX_PEERS (BD_N_AGENTS_MAX + 2)       /* every agent, the plant, the router */
#define BD_TICK_FRAMES_MAX 6                      /* 3 syncs, MC, Setpoint, Diag */
#define BD_ECHO_DEPTH 4                           /* own frames kept to tell their echo */
#define BD_FD_NEIGHBOURS_MAX (BD_TAG_SLOTS - 2)   /* AUTH-34: a tag slot each, the plant's and
                                                     the router's beside them */
#define BD_TAG_KEYS_MAX (BD_TAG_SLOTS + BD_FD_NEIGHBOURS_MAX)   /* its tags' keys, its
                                                     neighbours' tags' keys to it */

/* Errors of bd_agent_init (and of the config loader, which adds its own). */
#define BD_ERR_PARAMS 10        /* a parameter outside what the runtime can hold */
#define BD_ERR_MISSING_KEY 11   /* CFG-8: no verification key of a sender of an input */
#define BD_ERR_BOOT 12          /* boot counter exhausted, or persisting it failed */
#define BD_ERR_CRYPTO 13        /* the CMAC primitive failed */
#define BD_ERR_PRICE_KEY 14     /* AUTH-31: signed_price without the router's public key, or
                                   a build without the signed price (BD_SIGNED_PRICE 0) */

/* Every configuration value as the runtime uses it (spec sections 3, 4, 9.1, 10, 11),
 * integers only. Times in ns: rne(seconds * 1e9) of the binary64 values. */
typedef struct {
    uint32_t id;                  /* 1..BD_N_AGENTS_MAX */
    uint32_t fleet_size;          /* 0: unknown (RX-6 not checked) */
    int32_t pinned;               /* 0/1 (CTRL-5) */
    uint32_t resilient_f;         /* W-MSR F, 0: off (WMSR-1) */
    int32_t lambda0;              /* q24(lambda0) */
    bd_ctrl_config ctrl;          /* KTS, HTS, TSQ, BAND, D, ft exponent (CTRL-1..3) */
    uint32_t n_neighbours;
    uint32_t neighbour_id[BD_MAX_NEIGHBOURS];
    int32_t neighbour_weight[BD_MAX_NEIGHBOURS];   /* q24(weight) */
    /* SP-1: P = ((lambda * sp_gain + 2^39) >> 40) - sp_offset, clipped to [sp_lo, sp_hi] */
    int64_t sp_gain;
    int64_t sp_offset;
    int32_t sp_lo;
    int32_t sp_hi;
    int32_t idle_lambda;          /* q24(beta * (1 + m)) (CMD-3) */
    int64_t period_ns;            /* Ts */
    int64_t neighbour_timeout_ns; /* neighbour_periods * Ts (LIVE-2) */
    int64_t price_timeout_ns;     /* STATE-2 */
    int64_t status_timeout_ns;
    int64_t untrusted_ns;         /* RX-12 */
    int64_t sync_ns;              /* AUTH-13: the sync cadence (ER_Price_Sync's cycle at Ts) */
    int64_t hello_ns;             /* AUTH-15: 0.1 * sync */
    int64_t join_ns;              /* AUTH-26: the join window, 0.2 * sync (0: none) */
    int32_t lambda_min;           /* q24 limits (CFG-7) */
    int32_t lambda_max;
    int32_t rho_min;
    int32_t rho_max;
    int32_t price_step_max;
    int32_t lambda_step_max;
    uint32_t price_persist;
    uint32_t untrusted_after;
    /* CMD-5: the accepted GainK/GainH raw ranges (the binary64 bounds, as raw values) */
    uint32_t gain_k_raw_min;
    uint32_t gain_k_raw_max;
    uint32_t gain_h_raw_min;
    uint32_t gain_h_raw_max;
    /* TX-7: the MC frame every tick (tx_event 0), or when wire lambda moved more than
     * tx_threshold (q24) from the one last sent, the State changed, or tx_heartbeat ticks
     * passed since the last one (tx_event 1) */
    uint32_t tx_event;
    int32_t tx_threshold;
    uint32_t tx_heartbeat;
    /* GEN-1, RX-2: 1 on a CAN FD bus (the DBC's FD twin): every frame sent as FD with the
     * bit-rate switch, classic frames received are malformed; 0: classic CAN */
    uint32_t fd;
    /* AUTH-34: 0 on an FD bus is the default, AGENT_<i>_MC and its sync with a λ tag per
     * receiver (32 bytes); 1: without them, 8 bytes under the node key as on classic CAN
     * (--no-lambda-tags, [security] lambda_tags = false: dbc/bess_ded_fd_untagged.dbc) */
    uint32_t no_lambda_tags;
    /* AUTH-31..33: 1 takes only the router's signed price ([security] signed_price) */
    uint32_t signed_price;
} bd_agent_params;

/* The node's key material (CFG-8, AUTH-1..3, AUTH-20). */
typedef struct {
    char node[BD_LABEL_MAX + 1];          /* "agent_<id>" */
    uint8_t key[BD_KEY_BYTES];            /* own signing key */
    uint32_t boot;                        /* boot counter stored before this start */
    int32_t insecure;                     /* 1: --insecure (all-zero master, boot 1) */
    int32_t has_master;                   /* 1: derive any sender's key from master (a
                                             simulated fleet; insecure: the zero key) */
    uint8_t master[BD_KEY_BYTES];
    uint32_t n_peers;
    char peer_label[BD_MAX_PEERS][BD_LABEL_MAX + 1];
    uint8_t peer_key[BD_MAX_PEERS][BD_KEY_BYTES];
    uint16_t peer_floor[BD_MAX_PEERS];    /* AUTH-21: lowest boot accepted (0: none) */
    /* AUTH-28..30: the agent's frame keys, AGENT_<id>_Setpoint's and AGENT_<id>_Diag's
     * (it signs), PLANT_<id>_Status's and its ER_Command key (it verifies); has_master:
     * derived instead */
    int32_t has_frame_keys;
    uint8_t setpoint_key[BD_KEY_BYTES];
    uint8_t status_key[BD_KEY_BYTES];
    uint8_t diag_key[BD_KEY_BYTES];
    uint8_t command_key[BD_KEY_BYTES];    /* AUTH-30: [command_keys], its own (it verifies) */
    uint16_t status_floor;                /* AUTH-21: the plant's, if not in peer_floor */
    /* AUTH-34 (CAN FD): [lambda_tag_keys], the pair keys K_tag(sender -> receiver), each
     * pair as its TagRx codes (an agent its id, BD_TAG_RX_PLANT, BD_TAG_RX_ROUTER); with
     * the floor of the sender of a pair to this node if [peers] does not list it
     * (AUTH-21); has_master: derived instead */
    uint32_t n_tags;
    uint8_t tag_pair[BD_TAG_KEYS_MAX][2];
    uint8_t tag_key[BD_TAG_KEYS_MAX][BD_KEY_BYTES];
    uint16_t tag_floor[BD_TAG_KEYS_MAX];
    /* Persist a new boot counter before it is used (write-ahead, AUTH-3); 0 on
     * success. NULL: nothing persisted (insecure mode, tests). */
    int (*persist_boot)(void *ctx, uint32_t boot);
    void *persist_ctx;
    /* AUTH-31: the router's Ed25519 public key ([price_signature] of the key file: its
     * verify_key, or the public key of its sign_key) and the key set's fleet ID, which
     * the signed message covers */
    int32_t has_price_key;
    uint8_t price_key[BD_ED25519_PUBLIC_BYTES];
    uint8_t fleet_id[8];
} bd_keyring;

/* The counters' indices BD_C_* and BD_C_COUNT: bd_contract.h, generated from
 * firmware_py's contract.AGENT_COUNTERS. */

/* The counter's name as firmware_py counts it ("dlc", "deadline_miss", ...); NULL if
 * out of range. */
const char *bd_counter_name(int counter);

/* Events for the platform's log: every counter increment (event = BD_C_*, frame_id the
 * frame's ID where there is one, detail the new count) and the state changes
 * (BD_EV_STATE, detail = new state). */
#define BD_EV_STATE 100
typedef void (*bd_event_fn)(void *ctx, int event, uint32_t frame_id, uint32_t detail);

/* ---- the agent's state: private to the runtime (src/agent*.c), public only for static
 * allocation. Laid out for a small MCU: about 3 KB with 31 neighbours (firmware_c/README.md). */
#define BD_RX_UNTRUSTED 0x01u     /* bd_rx_slot.flags: untrusted_until is set */
#define BD_RX_HAS_FV 0x02u        /* the last accepted freshness value is known */
#define BD_RX_LOST 0x04u          /* its sender timed out: LOST_WINDOWS windows tried */
#define BD_RX_JOIN 0x08u          /* joining: fv is the newest sync's FV (AUTH-26) */
#define BD_RX_BACK 0x10u          /* back is set (AUTH-27) */
#define BD_RX_SPOKE 0x20u         /* a frame was taken since the latest boot advance (AUTH-27) */
#define BD_RX_PENDING 0x40u       /* pending is set: a boot advance held (AUTH-35) */
typedef struct {
    int64_t untrusted_until;
    uint64_t fv;                  /* the last accepted freshness value */
    uint64_t pending;             /* a held boot advance's FV - 1 (AUTH-35) */
    uint16_t id;                  /* the input's frame ID */
    uint16_t sync_id;             /* its <name>_Sync */
    uint16_t streak;              /* consecutive receive failures (RX-13) */
    uint16_t seen;                /* bit k: the frame of FV fv - k was accepted (AUTH-25) */
    uint8_t key_index;            /* its sender's verification key, in bd_agent.key */
    uint8_t flags;                /* BD_RX_* */
    uint16_t back_boot;           /* fv before the latest boot advance (AUTH-27), split: */
    uint32_t back_count;          /* it fits the struct's padding, no RAM added */
} bd_rx_slot;

#define BD_NB_HAS_LAM 0x01u
#define BD_NB_HAS_RX 0x02u
#define BD_NB_ALIVE 0x04u
typedef struct {
    int64_t last_rx;
    int32_t lam;                  /* last lambda_j accepted (Q24) */
    uint8_t state;                /* its last State */
    uint8_t flags;                /* BD_NB_* */
} bd_neighbour;

typedef struct {
    uint8_t data[BD_ECHO_DEPTH][BD_FRAME_DATA];
    uint16_t id;
    uint8_t len;                  /* its frames' length (AUTH-34: MC's on FD) */
    uint8_t n;                    /* frames remembered (<= BD_ECHO_DEPTH) */
    uint8_t next;
} bd_echo;

#if BD_SIGNED_PRICE
/* AUTH-32: one price segment as the router signs it (raw wire values) */
typedef struct {
    int32_t rho;                  /* ER_Price.Rho */
    uint16_t boot;                /* the router's boot when it signed */
    uint16_t number;              /* the segment number, mod BD_SIG_SEGMENT_MOD */
    uint8_t valid;                /* ER_Price.PriceValid */
} bd_signed_segment;

/* AUTH-32: the ER_PriceSig transfer being reassembled and the newest verified segment
 * (firmware_py pricesig.PriceSigReceiver) */
typedef struct {
    uint64_t part[BD_SIG_PAGES];  /* pages 1..BD_SIG_PAGES: their Signature values */
    bd_signed_segment header;     /* page 0 of the transfer under way */
    bd_signed_segment current;    /* the newest verified signed segment */
    uint16_t have;                /* bit k - 1: page k held */
    uint8_t has_header, has_current;
    uint8_t signature[BD_ED25519_SIG_BYTES];   /* current's */
    uint8_t key[BD_ED25519_PUBLIC_BYTES];      /* the router's public key */
    uint8_t fleet[8];                          /* the key set's fleet ID */
    uint32_t verifications;       /* signatures verified (a repeat costs none) */
} bd_price_sig;
#endif

#define BD_RX_PRICE 0
#define BD_RX_COMMAND 1
#define BD_RX_STATUS 2
#define BD_RX_MC0 3               /* neighbour j's MC: slot BD_RX_MC0 + j */
#define BD_N_ECHO 6               /* MC, Setpoint, Diag, MC_, Setpoint_, Diag_Sync */

typedef struct {
    bd_agent_params p;
    bd_ctrl_config ctrl;          /* the constants in use (SET_GAINS changes KTS, HTS) */
    int32_t pinned;               /* 0/1 in use: p.pinned at start, PIN changes it (CMD-7) */
    bd_ctrl_state cs;
    uint32_t count[BD_C_COUNT];   /* saturating */
    uint32_t ticks;
    uint32_t state;               /* BD_STATE_* */
    int32_t fatal;                /* BD_ERR_BOOT / BD_ERR_CRYPTO: the node must stop */
    /* receive side */
    bd_rx_slot rx[BD_RX_MC0 + BD_MAX_NEIGHBOURS];
    bd_neighbour nb[BD_MAX_NEIGHBOURS];
    uint8_t key[BD_MAX_PEERS][BD_KEY_BYTES];
    uint8_t key_label[BD_MAX_PEERS];              /* 1..32 agent, 33 plant, 34 router */
    uint16_t key_floor[BD_MAX_PEERS];             /* AUTH-21: lowest boot of that sender */
    uint16_t sync_streak[BD_N_SYNC_IDS];          /* failure streak of each sync ID */
    uint16_t peer_boot[BD_N_SYNC_IDS];            /* a peer's known boot (0: none) */
    uint32_t n_rx;
    uint32_t n_keys;
    uint32_t n_listed;                            /* keys [0, n_listed) count as held for
                                                     the acceptance filter's peer syncs */
    int32_t insecure;
    int32_t derive;                               /* keys derived on demand from master */
    uint8_t master[BD_KEY_BYTES];
    uint32_t safety_rejections;
    uint32_t last_safety_cause;                   /* BD_SAFETY_CAUSE_* (0: none) */
    uint32_t last_safety_sender;
    /* inputs */
    int64_t price_rx;
    int64_t status_rx;
    int64_t now;
    int32_t price;
    int32_t candidate;
    uint32_t candidate_n;
    uint8_t has_price, has_price_rx, has_status_rx, price_fresh, status_fresh, plant_fault,
        power_limited, has_candidate;
    /* transmit side */
    uint8_t own_key[BD_KEY_BYTES];
    uint8_t setpoint_key[BD_KEY_BYTES];   /* AUTH-28: the own setpoint's link frame key */
    uint8_t diag_key[BD_KEY_BYTES];       /* AUTH-29: the own Diag's frame key */
    uint8_t command_key[BD_KEY_BYTES];    /* AUTH-30: the key of the commands to it */
    /* AUTH-34 (CAN FD): its λ tags' receivers (TagRx codes, 0: an empty slot) and keys,
     * and the key of each neighbour's tags to it (by neighbour index) */
    uint8_t tag_code[BD_TAG_SLOTS];
    uint8_t tag_key[BD_TAG_SLOTS][BD_KEY_BYTES];
    uint8_t tag_rx_key[BD_FD_NEIGHBOURS_MAX][BD_KEY_BYTES];
    int (*persist_boot)(void *ctx, uint32_t boot);
    void *persist_ctx;
    int64_t sync_next;
    int64_t hello_after;
    uint32_t boot;
    uint32_t tx_count[3];         /* MC, Setpoint, Diag: message counts under this boot */
    int32_t mc_last_lam;          /* TX-7: the lambda and State of the last MC frame sent, */
    uint32_t mc_last_state;       /* the ticks since (mc_age), whether one was sent yet */
    uint32_t mc_age;
    int32_t mc_has_last;
    int32_t sync_pending;         /* syncs due at the next tick (start, new boot) */
    int32_t hello_due;
    int64_t join_until;           /* AUTH-26: end of the join window (INT64_MAX: not begun) */
    int32_t joining;              /* AUTH-26: 1 until the join window is over */
    bd_echo echo[BD_N_ECHO];
    bd_event_fn on_event;
    void *event_ctx;
#if BD_SIGNED_PRICE
    bd_price_sig sig;             /* AUTH-31..33: used if p.signed_price */
#endif
} bd_agent;

/* Start an agent (spec 3, 4, AUTH-3): params must be valid (src/config.c checks them);
 * the boot counter keys->boot + 1 is persisted (keys->persist_boot) before any frame is
 * signed. Returns BD_OK or a BD_ERR_*. The agent copies what it needs of keys: the
 * keyring may live in flash or be discarded (a count wrap calls persist_boot, AUTH-5). */
int bd_agent_init(bd_agent *a, const bd_agent_params *p, const bd_keyring *keys,
                  bd_event_fn on_event, void *event_ctx);

/* One received frame at time t_ns (spec section 10). */
void bd_agent_rx(bd_agent *a, const bd_frame *f, int64_t t_ns);

/* The periodic step at t_ns (TICK-1): the frames to send, in order, into out[0..max-1];
 * returns how many (at most BD_TICK_FRAMES_MAX). */
size_t bd_agent_tick(bd_agent *a, int64_t t_ns, bd_frame *out, size_t max);

/* A runtime event of the loop: BD_C_DEADLINE_MISS, BD_C_SEND_FAILURE, BD_C_ERROR_FRAME,
 * BD_C_NOT_A_FRAME, BD_C_INVALID_FRAME, BD_C_RX_ERROR. */
void bd_agent_note(bd_agent *a, int counter, uint32_t n);

/* The IDs an acceptance filter must pass (firmware_py NodeIO.accepted_ids), sorted;
 * returns how many (writes at most max). */
size_t bd_agent_accepted_ids(const bd_agent *a, uint32_t *ids, size_t max);

/* The wire lambda (Q24) the agent sends now. */
int32_t bd_agent_lambda(const bd_agent *a);

/* Test hook of the node vectors' `setup` (AUTH-5 in seconds, not 2^24 frames): the own
 * message counts of MC, Setpoint and Diag. */
void bd_agent_set_tx_count(bd_agent *a, uint32_t mc, uint32_t setpoint, uint32_t diag);

/* For bindings and logs: a counter's value, the state, the resets so far. */
uint32_t bd_agent_counter(const bd_agent *a, int counter);
uint32_t bd_agent_state(const bd_agent *a);
uint32_t bd_agent_resets(const bd_agent *a);
uint32_t bd_agent_boot(const bd_agent *a);   /* the boot counter the agent signs under */
/* AUTH-32: the price signatures the agent verified so far (0 without the signed price) */
uint32_t bd_agent_sig_verifications(const bd_agent *a);
/* 0, or the BD_ERR_* that stopped the agent: no boot counter left at a count wrap
 * (AUTH-5), or the CMAC primitive failed. The node must stop (the reference raises). */
int32_t bd_agent_fatal(const bd_agent *a);

/* sizeof(bd_agent), sizeof(bd_agent_params), sizeof(bd_keyring): for bindings that
 * allocate them or mirror their layout. */
size_t bd_agent_size(void);
size_t bd_agent_params_size(void);
size_t bd_keyring_size(void);

#ifdef __cplusplus
}
#endif

#endif /* BESSDED_AGENT_H */
