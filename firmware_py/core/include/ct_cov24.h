#ifndef CT_COV24_H
#define CT_COV24_H
/* cov24.c: the covariance prediction P <- A P A^T + Q of the 24-state fusion filter at its fixed
 * size (ekf.c ct_covariance_predict's sums and order, the same bits) */

#define CT_COV24_N 24

/* 1 when the four n x n buffers do not overlap (ct_covariance_predict_24's restrict), n = CT_COV24_N */
int ct_cov24_disjoint(const double *A, const double *P, const double *Q, const double *T);
void ct_covariance_predict_24(const double *A, double *P, const double *Q,
                              double *T);

#endif
