/*
 * Platform pieces of the policy node, chosen at link time by the Makefile:
 * transport_socketcan.c + clock_posix.c for the real node, tests/fake_platform.c for unit tests.
 */
#ifndef EMBEDRL_PLATFORM_H
#define EMBEDRL_PLATFORM_H

#include <stdint.h>

#define CAN_FRAME_MAX_BYTES 64u /* CAN FD; classic frames use 8 */

typedef struct {
    uint32_t id;
    uint8_t len;
    uint8_t data[CAN_FRAME_MAX_BYTES];
} can_frame_t;

typedef enum {
    TRANSPORT_FAILED = -1,   /* the interface is gone or down: close it and open it again */
    TRANSPORT_TIMEOUT = 0,   /* nothing within the timeout (or a signal) */
    TRANSPORT_FRAME = 1,     /* *frame holds a data frame with one of the subscribed IDs */
    TRANSPORT_BUS_STATE = 2, /* an error frame changed the controller state: *bus_state */
} transport_event;

/* Open the CAN interface, subscribed (in the kernel, CAN_RAW_FILTER) to the standard-ID data frames
 * ids[0..count-1] only, and to the controller's error frames. 0 on success (the interface exists and
 * is up); otherwise -1 and transport_error() says why. fd: also send and receive CAN FD frames. */
int transport_open(const char *iface, const uint32_t *ids, unsigned count, int fd);
/* Wait up to timeout_ms for a frame or a bus-state change. bus_state: 0 active, 1 error passive,
 * 2 bus-off (node_bus_state). */
transport_event transport_recv(can_frame_t *frame, uint8_t *bus_state, uint32_t timeout_ms);
/* Send a frame: 0 on success, -1 if the interface refused it (bus-off, down, queue full). */
int transport_send(const can_frame_t *frame);
void transport_close(void);
/* Why the last transport_open failed. */
const char *transport_error(void);

/* Monotonic clock. */
uint32_t clock_ms(void);
uint32_t clock_us(void);
void sleep_ms(uint32_t ms);

#endif /* EMBEDRL_PLATFORM_H */
