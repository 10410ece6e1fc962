/*
 * Raw-integer frames over the cantools-generated codec (frames.h).
 */
#include "frames.h"

#include <string.h>

#include "bd_contract.h"
#include "bd_dbc.h"
#include "bessded/frame.h"

/* AUTH-34: a bd_frame holds the contract's longest frame (C99: no _Static_assert) */
typedef char bd_frame_holds_fd_mc[(BD_FD_MC_BYTES <= BD_FRAME_DATA) ? 1 : -1];

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
    m->target = (uint32_t)f.target + BD_TARGET_OFFSET;   /* the agent: raw + DBC offset */
    m->gain_k = f.gain_k;
    m->gain_h = f.gain_h;
    /* CMD-7: a PIN says which way in GainK (BD_PIN_ON / BD_PIN_OFF), with GainH = 0 */
    int pin_ok = f.command != BD_CMD_PIN
                 || ((f.gain_k == BD_PIN_ON || f.gain_k == BD_PIN_OFF) && f.gain_h == 0u);
    return (bd_dbc_er_command_command_is_in_range(f.command)
            && bd_dbc_er_command_target_is_in_range(f.target)
            && bd_dbc_er_command_gain_k_is_in_range(f.gain_k)
            && bd_dbc_er_command_gain_h_is_in_range(f.gain_h) && pin_ok) ? 0 : -1;
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

void bd_encode_diag(uint32_t counter, uint32_t page, const uint32_t *v, uint8_t d[8])
{
    /* the DBC's page layout (bd_diag_pages, firmware_c/gen_contract.py); Mac = 0 */
    uint64_t x = ((uint64_t)counter << BD_AGENT_DIAG_COUNTER_START)
                 | ((uint64_t)page << BD_AGENT_DIAG_PAGE_START);
    for (uint32_t k = 0u; k < bd_diag_page_signals[page]; ++k) {
        const bd_diag_field *f = &bd_diag_pages[page][k];
        uint64_t mask = (UINT64_C(1) << f->length) - 1u;
        x |= ((uint64_t)v[k] & mask) << f->start;
    }
    for (uint32_t b = 0u; b < 8u; ++b) {
        d[b] = (uint8_t)((x >> (8u * b)) & 0xFFu);
    }
}
