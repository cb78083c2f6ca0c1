/* The fusion filter's pose histories copied in part (ct_hist_sync.h).  Reference:
 * estimate/fusion_output.py PoseHistory.rewind_shadow, commit, _sync, _marked, _pushed and
 * estimate/fusion_rings.py KernelRing.copy_slots_from, take_position; the whole copy and the drop are
 * fusion.c's ct_fusion_hist_copy (Ring.copy_from, Ring.drop_newer_than).  The arrays after a copy
 * are the same bytes as after the whole copy. */
#include <string.h>

#include "coiltrack_core.h"

int64_t ct_hist_pushed(const int64_t *t, const int64_t *hc, int64_t cap, int64_t k, int64_t tk)
{
    int64_t n;
    if (t[k] != tk || hc[1] == 0)
        return cap;
    n = (hc[0] - 1 < 0 ? cap - 1 : hc[0] - 1) - k;      /* Ring.peek(0) - k */
    return n < 0 ? n + cap : n;
}

/* KernelRing._copy_range: slots [a, b) */
static void copy_range(int64_t *dt, double *dd, const int64_t *st, const double *sd, int64_t a, int64_t b)
{
    if (b <= a)
        return;
    memcpy(dt + a, st + a, (size_t)(b - a) * sizeof(int64_t));
    memcpy(dd + a * CT_HIST_WIDTH, sd + a * CT_HIST_WIDTH, (size_t)((b - a) * CT_HIST_WIDTH) * sizeof(double));
}

/* KernelRing.copy_slots_from: n slots from h (modulo cap) */
static void copy_slots(int64_t *dt, double *dd, const int64_t *st, const double *sd, int64_t cap, int64_t h,
                       int64_t n)
{
    int64_t e;
    if (h >= cap)
        h -= cap;
    e = h + n;
    if (e <= cap) {
        copy_range(dt, dd, st, sd, h, e);
    } else {
        copy_range(dt, dd, st, sd, h, cap);
        copy_range(dt, dd, st, sd, 0, e - cap);
    }
}

/* PoseHistory._marked */
static void marked(const int64_t *live_t, const int64_t *live_hc, const int64_t *sh_t, const int64_t *sh_hc,
                   int64_t cap, int64_t *mark)
{
    int64_t k;
    if (live_hc[1] == 0 || sh_hc[1] == 0) {
        mark[CT_HMK_VALID] = 0;
        return;
    }
    mark[CT_HMK_VALID] = 1;
    k = live_hc[0] - 1 < 0 ? cap - 1 : live_hc[0] - 1;
    mark[CT_HMK_LIVE_SLOT] = k;
    mark[CT_HMK_LIVE_T] = live_t[k];
    k = sh_hc[0] - 1 < 0 ? cap - 1 : sh_hc[0] - 1;
    mark[CT_HMK_SHADOW_SLOT] = k;
    mark[CT_HMK_SHADOW_T] = sh_t[k];
}

void ct_hist_sync(int64_t *live_t, double *live_d, int64_t *live_hc, int64_t *sh_t, double *sh_d, int64_t *sh_hc,
                  int64_t cap, int64_t *mark, int to_shadow, int64_t t_us)
{
    int64_t *dt = to_shadow ? sh_t : live_t, *dhc = to_shadow ? sh_hc : live_hc;
    double *dd = to_shadow ? sh_d : live_d;
    const int64_t *st = to_shadow ? live_t : sh_t, *shc = to_shadow ? live_hc : sh_hc;
    const double *sd = to_shadow ? live_d : sh_d;
    int64_t sl, ss, nl, ns, lo, h;
    int whole = 1;
    if (mark[CT_HMK_VALID]) {
        sl = mark[CT_HMK_LIVE_SLOT];
        ss = mark[CT_HMK_SHADOW_SLOT];
        nl = ct_hist_pushed(live_t, live_hc, cap, sl, mark[CT_HMK_LIVE_T]);
        ns = ct_hist_pushed(sh_t, sh_hc, cap, ss, mark[CT_HMK_SHADOW_T]);
        if (nl + ns < cap) {
            copy_slots(dt, dd, st, sd, cap, sl + 1, nl);
            copy_slots(dt, dd, st, sd, cap, ss + 1, ns);
            dhc[0] = shc[0];
            dhc[1] = shc[1];
            whole = 0;
        }
    }
    if (whole) {
        ct_fusion_hist_copy(dt, dd, dhc, st, sd, shc, cap, to_shadow, t_us);
    } else if (to_shadow) {
        /* Ring.drop_newer_than (as ct_fusion_hist_copy's) */
        lo = ct_times_index_at_or_after(dt, cap, dhc[0], dhc[1], t_us + 1);
        h = dhc[0] - (dhc[1] - lo);
        dhc[0] = h < 0 ? h + cap : h;
        dhc[1] = lo;
    }
    marked(live_t, live_hc, sh_t, sh_hc, cap, mark);
}
