// Included first (-include) in every translation unit of the host run over the
// real Spresense library code (make hostlib): the few things NuttX gives those
// sources that a Linux host does not. The NuttX headers themselves come after
// the host's own (-idirafter), so <stdlib.h> and friends are glibc's.
#ifndef CUBECAM_HOSTLIB_NUTTX_HOST_H
#define CUBECAM_HOSTLIB_NUTTX_HOST_H

#include <semaphore.h>

// nuttx/compiler.h: the pointer qualifier of NuttX's declarations, empty on ARM.
#define FAR

#ifdef __cplusplus
extern "C" {
#endif
// NuttX's sem_wait(), checked: a semaphore taken while interrupts are off
// (noInterrupts(), "cpsid i") faults the board as soon as it is contended,
// because the task cannot be switched out. hostlib/board.cpp records it.
int hostlib_sem_wait(sem_t* sem);
// NuttX's libc has itoa(), which the core's String uses.
char* itoa(int value, char* str, int radix);
#ifdef __cplusplus
}
#endif

#define sem_wait hostlib_sem_wait

#endif
