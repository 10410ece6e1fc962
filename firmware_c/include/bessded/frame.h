/*
 * One CAN frame as the firmware sees it (docs/firmware-spec.md section 10): what the
 * platform's receive hands in and what the runtime hands out to send.
 */
#ifndef BESSDED_FRAME_H
#define BESSDED_FRAME_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define BD_FRAME_EXT 0x01u   /* a 29-bit identifier */
#define BD_FRAME_RTR 0x02u   /* a remote frame */
#define BD_FRAME_FD 0x04u    /* a CAN FD frame */
#define BD_FRAME_ERR 0x08u   /* an error frame */
#define BD_FRAME_BRS 0x10u   /* a CAN FD frame sent with the bit-rate switch */
/* The longest frame of the contract: AGENT_<i>_MC and its sync on CAN FD, 8 bytes and
 * their tag slots (AUTH-34; src/frames.c checks it against the DBC's BD_FD_MC_BYTES). */
#define BD_FRAME_DATA 32

typedef struct {
    uint32_t id;          /* 11-bit (or 29-bit with BD_FRAME_EXT) identifier */
    uint8_t len;          /* data length in bytes (up to 64 received on FD; data holds
                             the first BD_FRAME_DATA) */
    uint8_t flags;        /* BD_FRAME_* */
    uint8_t data[BD_FRAME_DATA];
} bd_frame;

#ifdef __cplusplus
}
#endif

#endif /* BESSDED_FRAME_H */
