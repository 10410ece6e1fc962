/*
 * A minimal Cortex-M4 image of the agent, to measure what the firmware costs on an MCU
 * (make arm-size; firmware_c/README.md): the core, the runtime, the generated codec and
 * SecOC, an agent with 63 neighbours (a 64-agent fleet's most) in .bss, its parameters in flash. The board's side
 * of the seam (the CAN controller, a timer, the AES engine behind bd_cmac_aes128) is
 * stood in for by the stubs below, so they are not counted.
 */
#include <stddef.h>
#include <stdint.h>

#include "bessded/agent.h"

static bd_agent agent;            /* the whole runtime state: .bss */

/* stand-in for the MCU's AES/CMAC engine (hardware or an HSM): the crypto seam */
int bd_cmac_aes128(const uint8_t key[BD_KEY_BYTES], const uint8_t *msg, size_t len,
                   uint8_t tag[16])
{
    for (size_t k = 0u; k < 16u; ++k) {
        tag[k] = (uint8_t)(key[k] ^ (k < len ? msg[k] : 0u));
    }
    return 0;
}

/* stand-ins for the CAN driver and the timer */
volatile uint32_t can_rx_id;
volatile uint8_t can_rx_data[8];
volatile uint32_t can_tx_id;
volatile uint8_t can_tx_data[8];
volatile int64_t timer_ns;

static const bd_agent_params params = {
    .id = 1u,
    .fleet_size = BD_N_AGENTS_MAX,
    .n_neighbours = BD_MAX_NEIGHBOURS,
    .ctrl = {BD_KIND_RESET, 10737418, 21474836, 10737418, 1678, 0u, 1u, 1u},
    .period_ns = 10000000,
    .neighbour_timeout_ns = 30000000,
    .price_timeout_ns = 250000000,
    .status_timeout_ns = 250000000,
    .untrusted_ns = 1000000000,
    .sync_ns = 1000000000,
    .hello_ns = 100000000,
    .lambda_min = -167772160,
    .lambda_max = 167772160,
    .rho_max = 83886080,
    .price_step_max = 8388608,
    .lambda_step_max = 1677722,
    .price_persist = 3u,
    .untrusted_after = 5u,
    .sp_gain = 606814815,
    .sp_offset = 1800,
    .sp_lo = -10000,
    .sp_hi = 10000,
    .gain_k_raw_max = BD_GAIN_RAW_MAX,
    .gain_h_raw_max = BD_GAIN_RAW_MAX,
};

int main(void);

int main(void)
{
    static const bd_keyring keys = {.insecure = 1};   /* a board keeps it in flash */
    bd_agent_params p = params;
    for (uint32_t j = 0u; j < BD_MAX_NEIGHBOURS; ++j) {
        p.neighbour_id[j] = j + 2u;
        p.neighbour_weight[j] = 1 << 24;
    }
    if (bd_agent_init(&agent, &p, &keys, NULL, NULL) != BD_OK) {
        return 1;
    }
    for (;;) {
        bd_frame f = {can_rx_id, 8u, 0u, {0}};
        bd_frame out[BD_TICK_FRAMES_MAX];
        for (size_t k = 0u; k < 8u; ++k) {
            f.data[k] = can_rx_data[k];
        }
        bd_agent_rx(&agent, &f, timer_ns);
        size_t n = bd_agent_tick(&agent, timer_ns, out, BD_TICK_FRAMES_MAX);
        for (size_t k = 0u; k < n; ++k) {
            can_tx_id = out[k].id;
            for (size_t b = 0u; b < 8u; ++b) {
                can_tx_data[b] = out[k].data[b];
            }
        }
    }
}
