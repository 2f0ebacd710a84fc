/*
 * Start-up of the bare-metal Cortex-M4 ports (example.c, gateway.c): the vector table the core
 * reads at 0x0, .data copied and .bss zeroed as the linker script (cortex_m4.ld) lays them out,
 * then main().
 */
#include <stdint.h>

int main(void);

/* linker script symbols: addresses only */
extern uint32_t _data_load[], _data_start[], _data_end[], _bss_start[], _bss_end[];
extern uint32_t _stack_top[];
void reset_handler(void);
void default_handler(void);

void default_handler(void)
{
    for (;;) {
    }
}

void reset_handler(void)
{
    /* the linker's symbols are addresses, not objects: work with word counts */
    const uintptr_t data_words = ((uintptr_t)_data_end - (uintptr_t)_data_start) / 4U;
    const uintptr_t bss_words = ((uintptr_t)_bss_end - (uintptr_t)_bss_start) / 4U;
    for (uintptr_t i = 0U; i < data_words; i++) {
        _data_start[i] = _data_load[i];
    }
    for (uintptr_t i = 0U; i < bss_words; i++) {
        _bss_start[i] = 0U;
    }
    (void)main();
    default_handler();
}

/* Initial stack pointer, reset, NMI, HardFault, then the faults and system handlers. */
typedef void (*vector)(void);
__attribute__((section(".vectors"), used)) static const vector vectors[16] = {
    (vector)(uintptr_t)_stack_top, reset_handler, default_handler, default_handler,
    default_handler, default_handler, default_handler, 0, 0, 0, 0, default_handler,
    default_handler, 0, default_handler, default_handler};
