/* Minimal Cortex-M4F start-up for running the unit tests under QEMU
   (mps2-an386) with semihosting: exit(n) becomes QEMU's exit status. */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

extern uint32_t _estack, __data_load, __data_start, __data_end, __bss_start, __bss_end;
extern void initialise_monitor_handles(void);
extern void __libc_init_array(void);
extern int main(void);

void *__dso_handle = 0;
void _init(void) {}
void _fini(void) {}

/* Any fault ends the run with a status no test produces. */
void Default_Handler(void) { exit(99); }

void Reset_Handler(void) {
    memcpy(&__data_start, &__data_load, (size_t)((char *)&__data_end - (char *)&__data_start));
    memset(&__bss_start, 0, (size_t)((char *)&__bss_end - (char *)&__bss_start));
    /* Enable the FPU (CP10, CP11 full access). */
    *(volatile uint32_t *)0xE000ED88 |= 0xFu << 20;
    __asm volatile("dsb\n\tisb");
    initialise_monitor_handles();
    __libc_init_array();
    exit(main());
}

__attribute__((section(".vectors"), used)) static void (*const vectors[16])(void) = {
    (void (*)(void))&_estack, Reset_Handler,   Default_Handler, Default_Handler,
    Default_Handler,          Default_Handler, Default_Handler, 0,
    0,                        0,               0,               Default_Handler,
    Default_Handler,          0,               Default_Handler, Default_Handler,
};
