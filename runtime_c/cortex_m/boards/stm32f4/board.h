/*
 * The board file of an STM32F405 (QEMU's netduinoplus2): registers from ST's reference manual RM0090.
 * Flash at 0x08000000 (1 MiB, aliased at 0), SRAM at 0x20000000 (128 KiB). The link is USART1 (0x40011000,
 * NVIC line 37; QEMU's first -serial), the diagnostics line USART2 (0x40004400; the second -serial), the
 * timer TIM2 (0x40000000), a 32-bit up counter. The core runs at 168 MHz from the PLL on this part (the clock
 * the cycle model names; flash with 5 wait states at 3.3 V, RM0090 table 10); QEMU's model runs TIM2 at
 * 1 GHz of virtual time, one tick per instruction under -icount shift=0, and needs no clock set-up (its RCC
 * is not modelled), so none is done here: on the part, RCC and the PLL come first.
 */
#ifndef EMBEDRL_BOARD_H
#define EMBEDRL_BOARD_H

#include <stdbool.h>
#include <stdint.h>

#include "board_common.h"

#define BOARD_REG(addr) (*(volatile uint32_t *)(addr))

#define BOARD_CPU_HZ 168000000u   /* SYSCLK from the PLL */
#define BOARD_TIMER_HZ 84000000u  /* TIM2 on APB1 (42 MHz, timer clock x2) at this SYSCLK */
#define BOARD_TIMER_MASK 0xFFFFFFFFu /* a 32-bit counter: tick differences wrap at 2^32 */

/* USART (RM0090 section 30.6): SR (RXNE bit 5, TC bit 6, TXE bit 7), DR, BRR, CR1 (RE bit 2, TE bit 3,
 * RXNEIE bit 5, UE bit 13). */
#define USART1_BASE 0x40011000u /* the CAN link (SLCAN) */
#define USART2_BASE 0x40004400u /* the diagnostics line */
#define USART_SR(b) BOARD_REG((b) + 0x00u)
#define USART_DR(b) BOARD_REG((b) + 0x04u)
#define USART_BRR(b) BOARD_REG((b) + 0x08u)
#define USART_CR1(b) BOARD_REG((b) + 0x0Cu)
#define USART_SR_RXNE 0x20u
#define USART_SR_TXE 0x80u
#define USART_CR1_RE 0x4u
#define USART_CR1_TE 0x8u
#define USART_CR1_RXNEIE 0x20u
#define USART_CR1_UE 0x2000u
#define USART1_BRR 0x5Bu /* 921,600 baud from APB2's 84 MHz: 84 MHz / (16 x 5.6875) = 923,077 (+0.2 %) */
#define USART2_BRR 0x2Eu /* 921,600 baud from APB1's 42 MHz: 42 MHz / (16 x 2.875) = 913,043 (-0.9 %) */
#define BOARD_LINK_IRQ 37u     /* USART1 global interrupt (RM0090 table 61) */

/* General-purpose timer TIM2 (RM0090 section 18.4): CR1 (CEN bit 0), EGR (UG bit 0), CNT, PSC, ARR. */
#define TIM2_BASE 0x40000000u
#define TIM_CR1(b) BOARD_REG((b) + 0x00u)
#define TIM_EGR(b) BOARD_REG((b) + 0x14u)
#define TIM_CNT(b) BOARD_REG((b) + 0x24u)
#define TIM_PSC(b) BOARD_REG((b) + 0x28u)
#define TIM_ARR(b) BOARD_REG((b) + 0x2Cu)
#define TIM_CR1_CEN 0x1u
#define TIM_EGR_UG 0x1u

#define NVIC_ISER(n) BOARD_REG(0xE000E100u + 4u * (n))

static inline void board_uarts_open(void)
{
    USART_BRR(USART1_BASE) = USART1_BRR;
    USART_BRR(USART2_BASE) = USART2_BRR;
    USART_CR1(USART2_BASE) = USART_CR1_UE | USART_CR1_TE;
    USART_CR1(USART1_BASE) = USART_CR1_UE | USART_CR1_TE | USART_CR1_RE | USART_CR1_RXNEIE;
    NVIC_ISER(BOARD_LINK_IRQ / 32u) = 1u << (BOARD_LINK_IRQ % 32u);
}

static inline void board_link_close(void)
{
    USART_CR1(USART1_BASE) = 0u;
}

static inline void board_uart_put(bool diag, uint8_t byte)
{
    uint32_t base = diag ? USART2_BASE : USART1_BASE;
    while ((USART_SR(base) & USART_SR_TXE) == 0u) {
    }
    USART_DR(base) = byte;
}

static inline void board_link_rx_ack(void)
{
    /* RXNE clears when DR is read (board_link_rx_byte) */
}

static inline bool board_link_rx_ready(void)
{
    return (USART_SR(USART1_BASE) & USART_SR_RXNE) != 0u;
}

static inline uint8_t board_link_rx_byte(void)
{
    return (uint8_t)(USART_DR(USART1_BASE) & 0xFFu);
}

static inline void board_timer_start(void)
{
    TIM_PSC(TIM2_BASE) = 0u;
    TIM_ARR(TIM2_BASE) = 0xFFFFFFFFu;
    TIM_EGR(TIM2_BASE) = TIM_EGR_UG; /* load the prescaler and restart the count from 0 */
    TIM_CR1(TIM2_BASE) = TIM_CR1_CEN;
}

static inline uint32_t board_timer_ticks(void)
{
    return TIM_CNT(TIM2_BASE);
}

#endif /* EMBEDRL_BOARD_H */
