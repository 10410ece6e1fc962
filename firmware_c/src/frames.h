/*
 * The agent's frames as raw integers (GEN-1, section 7/8/10), over the pack/unpack code
 * cantools generates from the DBC (build/gen/bd_dbc.c). Every agent's frames share agent
 * 1's layout (firmware_c/gen_contract.py checks it), so one packer serves every ID.
 * Internal to the runtime.
 */
#ifndef BESSDED_FRAMES_H
#define BESSDED_FRAMES_H

#include <stdint.h>

typedef struct { uint32_t counter, price_valid, segment; int32_t rho; } bd_price_msg;
/* target: the agent addressed (1..BD_N_AGENTS_MAX), not the raw Target */
typedef struct { uint32_t counter, command, target, gain_k, gain_h; } bd_command_msg;
typedef struct { uint32_t counter, state, resets; int32_t lambda; } bd_mc_msg;
typedef struct {
    uint32_t counter, fault_over_current, fault_voltage, fault_soc, power_limited;
} bd_status_msg;
typedef struct { uint32_t count, boot; } bd_sync_msg;

/* Decoders of a received 8-byte payload: 0, or -1 when a raw value lies outside its DBC
 * range (cause `range`, RX-9). The Counter of a secured frame is its low freshness bits. */
int bd_decode_price(const uint8_t d[8], bd_price_msg *m);
int bd_decode_command(const uint8_t d[8], bd_command_msg *m);
int bd_decode_mc(const uint8_t d[8], bd_mc_msg *m);
int bd_decode_status(const uint8_t d[8], bd_status_msg *m);
int bd_decode_sync(const uint8_t d[8], bd_sync_msg *m);

/* Encoders (Mac = 0: the caller signs). Values must lie in their DBC ranges (TX-6). */
void bd_encode_mc(uint32_t counter, uint32_t state, uint32_t resets, int32_t lambda,
                  uint8_t d[8]);
void bd_encode_setpoint(uint32_t counter, uint32_t enable, int32_t power, uint8_t d[8]);
void bd_encode_sync(uint32_t count, uint32_t boot, uint8_t d[8]);
/* AGENT_<i>_Diag page `page` with values[k] for the page's field k (bd_diag_pages), Mac =
 * 0 (the caller signs). */
void bd_encode_diag(uint32_t counter, uint32_t page, const uint32_t *values, uint8_t d[8]);

#endif /* BESSDED_FRAMES_H */
