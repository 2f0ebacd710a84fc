/*
 * Start-up for running C programs (the library's tests) on QEMU's mps2-an386 (Cortex-M4) with
 * newlib's semihosting library (librdimon): the vector table the core reads at 0x0, .data and
 * .bss set up, stdio connected to the host, main, and exit(), whose status becomes QEMU's.
 */
#include <stdint.h>
#include <stdlib.h>

/* linker script symbols: addresses only */
extern uint32_t _data_load[], _data_start[], _data_end[], _bss_start[], _bss_end[];
extern uint32_t _stack_top[];
extern void initialise_monitor_handles(void);
int main(void);
void reset_handler(void);
void fault_handler(void);

void fault_handler(void)
{
    exit(99); /* a fault ends the run with a status no test uses */
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
    initialise_monitor_handles();
    exit(main());
}

typedef void (*vector)(void);
__attribute__((section(".vectors"), used)) static const vector vectors[16] = {
    (vector)(uintptr_t)_stack_top, reset_handler, fault_handler, fault_handler, fault_handler,
    fault_handler, fault_handler, 0, 0, 0, 0, fault_handler, fault_handler, 0, fault_handler,
    fault_handler};
