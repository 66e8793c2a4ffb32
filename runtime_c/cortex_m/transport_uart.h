/* What the UART transport offers beyond platform.h: waiting for the channel to open, and what it measures
 * (reported on the diagnostics line). */
#ifndef EMBEDRL_TRANSPORT_UART_H
#define EMBEDRL_TRANSPORT_UART_H

#include <stdint.h>

void LinkRx_Handler(void); /* the link UART's receive interrupt */
/* Wait until the far end opens the channel ('O' or 'L', as a serial CAN adapter does), answering its
 * commands and time lines meanwhile: frames sent before would be lost (counted as send failures). */
void transport_await_open(void);
/* clock_ticks() when transport_recv last returned a frame (its line's terminator was parsed). */
uint32_t transport_frame_ticks(void);
/* clock_ticks() when transport_send last put a frame's final byte out. */
uint32_t transport_sent_ticks(void);
/* Received bytes dropped because the ring buffer was full. */
uint32_t transport_overflows(void);
/* Lines that were neither a valid frame nor a known command. */
uint32_t transport_bad_lines(void);

#endif /* EMBEDRL_TRANSPORT_UART_H */
