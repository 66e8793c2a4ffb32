/*
 * Minimal Cortex-M startup: vector table, .data copy, .bss zeroing, FPU enable, main, exit.
 *
 * The linker script (sections.ld) provides the symbols. exit() goes to newlib's semihosting
 * (rdimon), so under QEMU the exit status of main becomes the emulator's exit status.
 */
#include <stdint.h>
#include <stdlib.h>

#include "board.h"

extern uint32_t _sidata[], _sdata[], _edata[], _sbss[], _ebss[], _estack[];
int main(void);
void Reset_Handler(void);
void Default_Handler(void);

/* The firmware node's link receive interrupt (transport_uart.c); images without it never enable it. */
void LinkRx_Handler(void) __attribute__((weak, alias("Default_Handler")));
void SysTick_Handler(void) __attribute__((weak, alias("Default_Handler")));

#define CORE_VECTORS 16u

/* The initial stack pointer, reset, the fault handlers and the board's link receive interrupt (external
 * interrupt BOARD_LINK_IRQ); nothing else is enabled. */
__attribute__((section(".isr_vector"), used)) const uintptr_t vector_table[] = {
    (uintptr_t)_estack,         /* initial stack pointer */
    (uintptr_t)Reset_Handler,   /* reset */
    (uintptr_t)Default_Handler, /* NMI */
    (uintptr_t)Default_Handler, /* HardFault */
    (uintptr_t)Default_Handler, /* MemManage */
    (uintptr_t)Default_Handler, /* BusFault */
    (uintptr_t)Default_Handler, /* UsageFault */
    0u, 0u, 0u, 0u,             /* reserved */
    (uintptr_t)Default_Handler, /* SVCall */
    (uintptr_t)Default_Handler, /* DebugMonitor */
    0u,                         /* reserved */
    (uintptr_t)Default_Handler, /* PendSV */
    (uintptr_t)SysTick_Handler, /* SysTick (the firmware node's idle wake-up) */
    [CORE_VECTORS + BOARD_LINK_IRQ] = (uintptr_t)LinkRx_Handler,
};

void Default_Handler(void)
{
    exit(3); /* a fault: report it through semihosting instead of hanging */
}

void Reset_Handler(void)
{
    const uint32_t *src = _sidata;
    for (uint32_t *dst = _sdata; dst < _edata; ++dst) {
        *dst = *src++;
    }
    for (uint32_t *dst = _sbss; dst < _ebss; ++dst) {
        *dst = 0u;
    }
#if defined(__ARM_FP)
    /* Full access to coprocessors 10 and 11 (the FPU) before any float instruction. */
    *(volatile uint32_t *)0xE000ED88u |= 0xFu << 20;
    __asm__ volatile("dsb\n\tisb" ::: "memory");
#endif
    exit(main());
}
