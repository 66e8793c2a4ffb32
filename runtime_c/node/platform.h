/*
 * Platform pieces of the policy node, chosen at link time by the Makefile:
 * transport_socketcan.c + clock_posix.c for the real node, tests/fake_platform.c for unit tests.
 */
#ifndef EMBEDRL_PLATFORM_H
#define EMBEDRL_PLATFORM_H

#include <stdint.h>

typedef struct {
    uint32_t id;
    uint8_t len;
    uint8_t data[8];
} can_frame_t;

/* Open the CAN interface; 0 on success. */
int transport_open(const char *iface);
/* Wait up to timeout_ms for a frame: 1 received, 0 timeout, -1 error (interface gone). */
int transport_recv(can_frame_t *frame, uint32_t timeout_ms);
/* Send a frame: 0 on success. */
int transport_send(const can_frame_t *frame);
void transport_close(void);

/* Monotonic clock. */
uint32_t clock_ms(void);
uint32_t clock_us(void);

#endif /* EMBEDRL_PLATFORM_H */
