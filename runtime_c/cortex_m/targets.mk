# The Cortex-M targets, one block each: the single table that the Makefile (compiler flags, the linker
# script's memory sizes) and embedrl (export/target.py: QEMU machine, memory for the size report) read.
# <name>.CPU    GCC flags for the core
# <name>.BOARD  the board file (cortex_m/boards/<board>/board.h): the part's UARTs and timer
# <name>.FLASH  flash of the modelled part [KiB], at FLASH_AT
# <name>.FLASH_AT  where flash is mapped (0x00000000: QEMU mps2 code memory; 0x08000000: STM32)
# <name>.RAM    RAM of the modelled part [KiB], at 0x20000000
# <name>.QEMU   the qemu-system-arm machine that emulates the core
# <name>.STACK  the stack reserved at the top of RAM (linker size: 4K, 1536, ...)
# <name>.HEAP   the heap below it, for newlib's stdio in the test image (semihosting printf)
# <name>.TICK   guest instructions per timer tick under QEMU's -icount shift=0 (1 ns per instruction):
#               1e9 over the timer's clock in Hz (a fraction where it is not whole)
# <name>.PART   the part whose memory is modelled

cortex-m4.CPU := -mcpu=cortex-m4 -mthumb -mfpu=fpv4-sp-d16 -mfloat-abi=hard
cortex-m4.BOARD := stm32f4
cortex-m4.FLASH := 1024
cortex-m4.FLASH_AT := 0x08000000
cortex-m4.RAM := 128
cortex-m4.STACK := 4K
cortex-m4.HEAP := 8K
cortex-m4.QEMU := netduinoplus2
cortex-m4.TICK := 1
cortex-m4.PART := Cortex-M4F, STM32F405

cortex-m3.CPU := -mcpu=cortex-m3 -mthumb -mfloat-abi=soft
cortex-m3.BOARD := stm32f1
cortex-m3.FLASH := 128
cortex-m3.FLASH_AT := 0x08000000
cortex-m3.RAM := 8
cortex-m3.STACK := 2K
cortex-m3.HEAP := 2K
cortex-m3.QEMU := stm32vldiscovery
cortex-m3.TICK := 125/3
cortex-m3.PART := Cortex-M3 without FPU, STM32F100RB

cortex-m7.CPU := -mcpu=cortex-m7 -mthumb -mfpu=fpv5-d16 -mfloat-abi=hard
cortex-m7.BOARD := mps2
cortex-m7.FLASH := 2048
cortex-m7.FLASH_AT := 0x00000000
cortex-m7.RAM := 512
cortex-m7.STACK := 4K
cortex-m7.HEAP := 8K
cortex-m7.QEMU := mps2-an500
cortex-m7.TICK := 40
cortex-m7.PART := Cortex-M7 with double-precision FPU, STM32F7-class
