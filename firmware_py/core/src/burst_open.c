/*
 * A burst's opening for many sensors (include/ct_burst_open.h): the writes the Python reference
 * makes for each channel and each sensor when the fixed cycle opens a burst (thesis
 * 002_cd7f1fdb7fc67471.txt sec 5.3: one X, Y, Z burst serves every sensor).
 */
#include <stdint.h>
#include <string.h>

#include "coiltrack_core.h"

void ct_new_burst(int64_t n, uint8_t *done, int64_t *flags, int64_t *cnt)
{
    int64_t j;
    for (j = 0; j < n; ++j)
        done[j] = 0;
    for (j = 0; j < n; ++j)
        flags[j] = 0;
    cnt[1] += 1;
}

void ct_schedule(int64_t *tr, int64_t *sq, int64_t t_ref)
{
    tr[0] = t_ref;
    sq[0] = t_ref;
    sq[1] = 1;
    sq[2] = 0;
}
