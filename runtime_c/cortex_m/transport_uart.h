/* What the UART transport measures beyond platform.h (reported on the diagnostics line). */
#ifndef EMBEDRL_TRANSPORT_UART_H
#define EMBEDRL_TRANSPORT_UART_H

#include <stdint.h>

void LinkRx_Handler(void); /* the link UART's receive interrupt */
/* clock_ticks() when transport_recv last returned a frame (its line's terminator was parsed). */
uint32_t transport_frame_ticks(void);
/* clock_ticks() when transport_send last put a frame's final byte out. */
uint32_t transport_sent_ticks(void);
/* Received bytes dropped because the ring buffer was full. */
uint32_t transport_overflows(void);
/* Lines that were neither a valid frame nor a known command. */
uint32_t transport_bad_lines(void);

#endif /* EMBEDRL_TRANSPORT_UART_H */
