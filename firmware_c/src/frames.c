/*
 * Raw-integer frames over the cantools-generated codec (frames.h).
 */
#include "frames.h"

#include <string.h>

#include "bd_contract.h"
#include "bd_dbc.h"

int bd_decode_price(const uint8_t d[8], bd_price_msg *m)
{
    struct bd_dbc_er_price_t f;
    (void)bd_dbc_er_price_unpack(&f, d, 8u);
    m->counter = f.counter;
    m->price_valid = f.price_valid;
    m->segment = f.segment;
    m->rho = f.rho;
    return (bd_dbc_er_price_price_valid_is_in_range(f.price_valid)
            && bd_dbc_er_price_segment_is_in_range(f.segment)
            && bd_dbc_er_price_rho_is_in_range(f.rho)) ? 0 : -1;
}

int bd_decode_command(const uint8_t d[8], bd_command_msg *m)
{
    struct bd_dbc_er_command_t f;
    (void)bd_dbc_er_command_unpack(&f, d, 8u);
    m->counter = f.counter;
    m->command = f.command;
    m->target = f.target;
    m->gain_k = f.gain_k;
    m->gain_h = f.gain_h;
    return (bd_dbc_er_command_command_is_in_range(f.command)
            && bd_dbc_er_command_target_is_in_range(f.target)
            && bd_dbc_er_command_gain_k_is_in_range(f.gain_k)
            && bd_dbc_er_command_gain_h_is_in_range(f.gain_h)) ? 0 : -1;
}

int bd_decode_mc(const uint8_t d[8], bd_mc_msg *m)
{
    struct bd_dbc_agent_1_mc_t f;
    (void)bd_dbc_agent_1_mc_unpack(&f, d, 8u);
    m->counter = f.counter;
    m->state = f.state;
    m->resets = f.resets;
    m->lambda = f.lambda;
    return (bd_dbc_agent_1_mc_state_is_in_range(f.state)
            && bd_dbc_agent_1_mc_resets_is_in_range(f.resets)
            && bd_dbc_agent_1_mc_lambda_is_in_range(f.lambda)) ? 0 : -1;
}

int bd_decode_status(const uint8_t d[8], bd_status_msg *m)
{
    struct bd_dbc_plant_1_status_t f;
    (void)bd_dbc_plant_1_status_unpack(&f, d, 8u);
    m->counter = f.counter;
    m->fault_over_current = f.fault_over_current;
    m->fault_voltage = f.fault_voltage;
    m->fault_soc = f.fault_soc;
    m->power_limited = f.power_limited;
    return (bd_dbc_plant_1_status_power_is_in_range(f.power)
            && bd_dbc_plant_1_status_soc_is_in_range(f.soc)) ? 0 : -1;
}

int bd_decode_sync(const uint8_t d[8], bd_sync_msg *m)
{
    /* every <name>_Sync has ER_Price_Sync's layout (firmware_c/gen_contract.py) */
    struct bd_dbc_er_price_sync_t f;
    (void)bd_dbc_er_price_sync_unpack(&f, d, 8u);
    m->count = f.count;
    m->boot = f.boot;
    return (bd_dbc_er_price_sync_count_is_in_range(f.count)
            && bd_dbc_er_price_sync_boot_is_in_range(f.boot)) ? 0 : -1;
}

void bd_encode_mc(uint32_t counter, uint32_t state, uint32_t resets, int32_t lambda,
                  uint8_t d[8])
{
    struct bd_dbc_agent_1_mc_t f;
    (void)bd_dbc_agent_1_mc_init(&f);
    f.counter = (uint8_t)counter;
    f.state = (uint8_t)state;
    f.resets = (uint8_t)resets;
    f.lambda = lambda;
    (void)bd_dbc_agent_1_mc_pack(d, &f, 8u);
}

void bd_encode_setpoint(uint32_t counter, uint32_t enable, int32_t power, uint8_t d[8])
{
    struct bd_dbc_agent_1_setpoint_t f;
    (void)bd_dbc_agent_1_setpoint_init(&f);
    f.counter = (uint8_t)counter;
    f.enable = (uint8_t)enable;
    f.power_setpoint = (int16_t)power;
    (void)bd_dbc_agent_1_setpoint_pack(d, &f, 8u);
}

void bd_encode_sync(uint32_t count, uint32_t boot, uint8_t d[8])
{
    struct bd_dbc_er_price_sync_t f;
    (void)bd_dbc_er_price_sync_init(&f);
    f.count = count;
    f.boot = (uint16_t)boot;
    (void)bd_dbc_er_price_sync_pack(d, &f, 8u);
}

void bd_encode_diag(uint32_t frame_id, uint32_t counter, uint32_t page,
                    const uint32_t *v, uint8_t d[8])
{
    struct bd_dbc_agent_1_diag_t f;
    (void)bd_dbc_agent_1_diag_init(&f);
    f.counter = (uint8_t)counter;
    f.page = (uint8_t)page;
    /* the pages of firmware_py.runtime.AgentRuntime.DIAG_PAGES (tools/gen_dbc.py) */
    switch (page) {
    case 0:
        f.resets = (uint16_t)v[0];
        f.deadline_misses = (uint16_t)v[1];
        f.neighbours_alive = (uint8_t)v[2];
        f.state = (uint8_t)v[3];
        break;
    case 1:
        f.rejected_crc = (uint16_t)v[0];
        f.rejected_dlc = (uint16_t)v[1];
        f.rejected_range = (uint16_t)v[2];
        break;
    case 2:
        f.rejected_unknown_id = (uint16_t)v[0];
        f.rejected_impersonation = (uint16_t)v[1];
        f.repeated_counter = (uint16_t)v[2];
        break;
    case 3:
        f.lost_frames = (uint16_t)v[0];
        f.saturations = (uint16_t)v[1];
        f.neighbour_timeouts = (uint16_t)v[2];
        break;
    case 4:
        f.price_timeouts = (uint16_t)v[0];
        f.status_timeouts = (uint16_t)v[1];
        f.plant_faults = (uint16_t)v[2];
        break;
    case 5:
        f.foreign_frames = (uint16_t)v[0];
        f.foreign_ids = (uint16_t)v[1];
        f.interleaved_counters = (uint16_t)v[2];
        break;
    case 6:
        f.untrusted = (uint16_t)v[0];
        f.implausible_price = (uint16_t)v[1];
        f.implausible_lambda = (uint16_t)v[2];
        break;
    case 7:
        f.implausible_gains = (uint16_t)v[0];
        f.safety_sender = (uint16_t)v[1];
        f.safety_cause = (uint8_t)v[2];
        break;
    default:
        f.rejected_auth = (uint16_t)v[0];
        f.unsynced = (uint16_t)v[1];
        f.resyncs = (uint16_t)v[2];
        break;
    }
    (void)bd_dbc_agent_1_diag_pack(d, &f, 8u);
    d[0] = bd_e2e_crc(frame_id, d);
}

static uint8_t crc8_byte(uint8_t crc, uint8_t b)
{
    unsigned c = (unsigned)(crc ^ b);
    for (int k = 0; k < 8; k++) {
        c = (c & 0x80u) != 0u ? ((c << 1) ^ 0x1Du) : (c << 1);
    }
    return (uint8_t)(c & 0xFFu);
}

uint8_t bd_e2e_crc(uint32_t frame_id, const uint8_t d[8])
{
    uint8_t c = 0xFFu;
    c = crc8_byte(c, (uint8_t)(frame_id & 0xFFu));
    c = crc8_byte(c, (uint8_t)((frame_id >> 8) & 0xFFu));
    for (int k = 1; k < 8; k++) {
        c = crc8_byte(c, d[k]);
    }
    return (uint8_t)(c ^ 0xFFu);
}
