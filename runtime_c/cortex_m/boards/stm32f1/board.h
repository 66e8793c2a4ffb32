/*
 * The board file of an STM32F100RB (QEMU's stm32vldiscovery, the STM32VL-Discovery board): registers from
 * ST's reference manual RM0041. Flash at 0x08000000 (128 KiB, aliased at 0), SRAM at 0x20000000 (8 KiB).
 * The link is USART1 (0x40013800, NVIC line 37; QEMU's first -serial), the diagnostics line USART2
 * (0x40004400; the second -serial). The core runs at 24 MHz, the part's maximum (the clock the cycle model
 * names), from flash with 0 wait states (the value line has no flash latency setting). QEMU 7.2 models
 * this part's USARTs and SPIs but none of its timers (TIM1-4, 6, 7, 15-17 are unimplemented devices), so the
 * free-running timer is the core's SysTick on the processor clock: a 24-bit down counter, one tick per
 * 1/24 us (41 2/3 instructions under -icount shift=0). Its counts are read modulo 2^24
 * (BOARD_TIMER_MASK): a difference is exact up to 0.69 s (16,777,216 ticks), far longer than a step or
 * the test image's timed loops. QEMU does not model the RCC either, so no clock set-up is done here: on
 * the part, RCC (and the PLL for 24 MHz from the 8 MHz crystal) comes first.
 */
#ifndef EMBEDRL_BOARD_H
#define EMBEDRL_BOARD_H

#include <stdbool.h>
#include <stdint.h>

#include "board_common.h"

#define BOARD_REG(addr) (*(volatile uint32_t *)(addr))

#define BOARD_CPU_HZ 24000000u   /* SYSCLK: the value line's maximum */
#define BOARD_TIMER_HZ BOARD_CPU_HZ /* SysTick on the processor clock */
#define BOARD_TIMER_MASK 0xFFFFFFu  /* SysTick's 24-bit counter: tick differences are taken modulo 2^24 */
#define BOARD_TIMER_IS_SYSTICK 1    /* no timer left for the real-time clock's 1 ms interrupt */

/* USART (RM0041's USART registers, as on the STM32F4): SR (RXNE bit 5, TXE bit 7), DR, BRR, CR1 (RE bit 2, TE bit 3, RXNEIE bit 5,
 * UE bit 13). */
#define USART1_BASE 0x40013800u /* the CAN link (SLCAN) */
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
/* 921,600 baud from APB2's and APB1's 24 MHz: 24 MHz / (16 x 1.625) = 923,077 (+0.2 %) */
#define USART_BRR_921600 0x1Au
#define BOARD_LINK_IRQ 37u /* USART1 global interrupt (RM0041's vector table; QEMU wires it there) */

/* SysTick (ARMv7-M): CSR (ENABLE bit 0, CLKSOURCE bit 2: the processor clock), RVR, CVR (board_common.h). */
#define SYST_CSR_ENABLE_CORE 0x5u
#define SYST_RELOAD_MAX 0xFFFFFFu

#define NVIC_ISER(n) BOARD_REG(0xE000E100u + 4u * (n))

static inline void board_uarts_open(void)
{
    USART_BRR(USART1_BASE) = USART_BRR_921600;
    USART_BRR(USART2_BASE) = USART_BRR_921600;
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

/* SysTick from its full reload, without its interrupt. */
static inline void board_timer_start(void)
{
    SYST_CSR = 0u;
    SYST_RVR = SYST_RELOAD_MAX;
    SYST_CVR = 0u; /* any write clears the count: it reloads on the next tick */
    SYST_CSR = SYST_CSR_ENABLE_CORE;
}

/* Ticks counting up (SysTick counts down), modulo 2^24. */
static inline uint32_t board_timer_ticks(void)
{
    return (SYST_RELOAD_MAX - SYST_CVR) & BOARD_TIMER_MASK;
}

#endif /* EMBEDRL_BOARD_H */
