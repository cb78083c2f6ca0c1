/* The fusion filter's pose histories copied in part: estimate/fusion_output.py PoseHistory
 * (rewind_shadow, commit, _sync, _marked, _pushed) and estimate/fusion_rings.py KernelRing
 * (copy_slots_from, take_position). */
#ifndef CT_HIST_SYNC_H
#define CT_HIST_SYNC_H

#include <stdint.h>

/* PoseHistory.mark (int64): MK_VALID, MK_LIVE_SLOT, MK_LIVE_T, MK_SHADOW_SLOT, MK_SHADOW_T */
enum { CT_HMK_VALID = 0, CT_HMK_LIVE_SLOT = 1, CT_HMK_LIVE_T = 2, CT_HMK_SHADOW_SLOT = 3, CT_HMK_SHADOW_T = 4,
       CT_HMK_N = 5 };

/* _pushed: slots a ring (times t, head and count hc) pushed since its newest slot was k at time tk (cap when
 * unknown) */
int64_t ct_hist_pushed(const int64_t *t, const int64_t *hc, int64_t cap, int64_t k, int64_t tk);
/* PoseHistory.rewind_shadow (to_shadow 1: the shadow = the live history, then its entries newer than t_us
 * dropped) or commit (to_shadow 0: the live history = the shadow): the slots either pushed since the last
 * one (mark), or whole (ct_fusion_hist_copy); the mark set for the next */
void ct_hist_sync(int64_t *live_t, double *live_d, int64_t *live_hc, int64_t *sh_t, double *sh_d, int64_t *sh_hc,
                  int64_t cap, int64_t *mark, int to_shadow, int64_t t_us);

#endif /* CT_HIST_SYNC_H */
