/* The runtime's per-point loops, compiled: robust point-to-plane ICP of observed points onto a union of
   axis-aligned boxes (pallet6d_icp), the fit scores of posed models against the depth (pallet6d_fit), the
   registration test's pair counts (pallet6d_registration_counts), the viewing rays' hits and scores of posed
   pallets (pallet6d_along_rays, pallet6d_ray_scores) and the structure check's rays (pallet6d_cast_rays).

   ICP is the same algorithm as `refine._icp` in numpy (its docstring and `refine_pose`'s are the specification):
   per step, every observed point near the model's bounding box is matched with the closest point on the
   boxes' surface; matches within a correspondence distance that shrinks geometrically over the steps count,
   each with a Tukey weight; one Gauss-Newton step with a prior on the starting pose follows. numpy needs
   thousands of small calls per frame for this; here each pose is one loop. Per-point arithmetic in float
   (as the numpy path), sums and the 6x6 solve in double.

   Loaded with ctypes by `kernels.py`; the package builds it as an optional extension (setup.py). */
#include <math.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* The functions' signatures as kernels.py declares them: a library built from another version of this file (a
   stale in-place build) is refused there instead of being called with the wrong arguments. */
#define PALLET6D_KERNELS_ABI 4
int pallet6d_kernels_abi(void) { return PALLET6D_KERNELS_ABI; }

/* max / min as comparisons: fmaxf / fminf are library calls unless NaN semantics are given up (the points and
   boxes here are finite), these compile to single instructions and vectorise. */
static inline float maxf(float a, float b) { return a > b ? a : b; }
static inline float minf(float a, float b) { return a < b ? a : b; }

/* x rounded to the nearest integer, ties to even (numpy's round, nearbyint in the default rounding mode) for
   |x| < 2^51, without a library call: adding and taking away 1.5 * 2^52 leaves no fraction bits. Larger values
   (and inf, NaN) come out beyond any image and are dropped by the callers' range tests. */
static inline double round_even(double x) {
    const double magic = 6755399441055744.0;
    return (x + magic) - magic;
}

enum { MAX_BOXES = 256 };

/* Closest point on the surface of a union of boxes (structure of arrays: lo[a][b], hi[a][b]) to p, its outward
   normal and distance, among the n boxes idx[0..n) (ascending; every box that can be the closest). Inside a box,
   that box's nearest face; the first box wins ties, as argmin does. */
static void closest_on_boxes(const float p[3], const float lo[3][MAX_BOXES], const float hi[3][MAX_BOXES],
                             const uint8_t *idx, int64_t n, float q[3], float nrm[3], float *dist) {
    float o2[MAX_BOXES];
    o2[0] = INFINITY;                                       /* overwritten below (n >= 1) */
    for (int64_t i = 0; i < n; i++) {                       /* squared distance outside each box */
        int b = idx[i];
        float g0 = maxf(maxf(lo[0][b] - p[0], p[0] - hi[0][b]), 0.0f);
        float g1 = maxf(maxf(lo[1][b] - p[1], p[1] - hi[1][b]), 0.0f);
        float g2 = maxf(maxf(lo[2][b] - p[2], p[2] - hi[2][b]), 0.0f);
        o2[i] = g0 * g0 + g1 * g1 + g2 * g2;
    }
    int64_t jj = 0;
    for (int64_t i = 1; i < n; i++)
        if (o2[i] < o2[jj]) jj = i;
    int off = o2[jj] > 0.0f;
    float d = sqrtf(o2[jj]);
    if (!off) {
        /* in a box: each box the point is in at the depth below its nearest face, the others at their outside
           distance; the nearest wins */
        float best_d = INFINITY;
        for (int64_t i = 0; i < n; i++) {
            int b = idx[i];
            float below = INFINITY;
            for (int a = 0; a < 3; a++) below = minf(below, minf(p[a] - lo[a][b], hi[a][b] - p[a]));
            float db = o2[i] > 0.0f ? sqrtf(o2[i]) : maxf(below, 0.0f);
            if (db < best_d) { best_d = db; jj = i; off = o2[i] > 0.0f; }
        }
        d = best_d;
    }
    int j = idx[jj];
    for (int a = 0; a < 3; a++) q[a] = minf(maxf(p[a], lo[a][j]), hi[a][j]);
    if (off) {
        for (int a = 0; a < 3; a++) nrm[a] = (p[a] - q[a]) / d;
    } else {
        /* the nearest face, the first of -x -y -z +x +y +z */
        int f = 0;
        float fd = INFINITY;
        for (int s = 0; s < 6; s++) {
            int a = s % 3;
            float g = s < 3 ? p[a] - lo[a][j] : hi[a][j] - p[a];
            if (g < fd) { fd = g; f = s; }
        }
        int a = f % 3;
        nrm[0] = nrm[1] = nrm[2] = 0.0f;
        q[a] = f >= 3 ? hi[a][j] : lo[a][j];
        nrm[a] = f >= 3 ? 1.0f : -1.0f;
    }
    *dist = d;
}

/* out = a @ b for 4x4 row-major matrices (out may not alias a or b). */
static void mat4_mul(const double *a, const double *b, double *out) {
    for (int r = 0; r < 4; r++)
        for (int c = 0; c < 4; c++) {
            double s = 0.0;
            for (int i = 0; i < 4; i++) s += a[4 * r + i] * b[4 * i + c];
            out[4 * r + c] = s;
        }
}

/* Inverse of a rigid transform. */
static void rigid_inverse(const double *T, double *out) {
    memset(out, 0, 16 * sizeof(double));
    for (int r = 0; r < 3; r++) {
        for (int c = 0; c < 3; c++) out[4 * r + c] = T[4 * c + r];
        out[4 * r + 3] = -(T[r] * T[3] + T[4 + r] * T[7] + T[8 + r] * T[11]);
    }
    out[15] = 1.0;
}

/* The transform of a small motion: rotation vector w = delta[0:3], translation delta[3:6] (as numpy's
   `_exp_se3_batch`: Rodrigues' rotation, the translation taken as is). */
static void exp_se3(const double delta[6], double *T) {
    const double *w = delta;
    double th = sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]);
    double a = 1.0, b = 0.0;
    if (!(th < 1e-12)) { a = sin(th) / th; b = (1.0 - cos(th)) / (th * th); }
    double Kx[9] = {0.0, -w[2], w[1], w[2], 0.0, -w[0], -w[1], w[0], 0.0};
    memset(T, 0, 16 * sizeof(double));
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++) {
            double kk = 0.0;
            for (int i = 0; i < 3; i++) kk += Kx[3 * r + i] * Kx[3 * i + c];
            T[4 * r + c] = (r == c ? 1.0 : 0.0) + a * Kx[3 * r + c] + b * kk;
        }
    for (int r = 0; r < 3; r++) T[4 * r + 3] = delta[3 + r];
    T[15] = 1.0;
}

/* Solve H x = g for a symmetric positive definite 6x6 H (Cholesky); returns 0 when H is not. */
static int solve6(const double H[36], const double g[6], double x[6]) {
    double L[36] = {0.0};
    for (int i = 0; i < 6; i++)
        for (int j = 0; j <= i; j++) {
            double s = H[6 * i + j];
            for (int k = 0; k < j; k++) s -= L[6 * i + k] * L[6 * j + k];
            if (i == j) {
                if (!(s > 0.0)) return 0;
                L[6 * i + i] = sqrt(s);
            } else {
                L[6 * i + j] = s / L[6 * j + j];
            }
        }
    double y[6];
    for (int i = 0; i < 6; i++) {
        double s = g[i];
        for (int k = 0; k < i; k++) s -= L[6 * i + k] * y[k];
        y[i] = s / L[6 * i + i];
    }
    for (int i = 5; i >= 0; i--) {
        double s = y[i];
        for (int k = i + 1; k < 6; k++) s -= L[6 * k + i] * x[k];
        x[i] = s / L[6 * i + i];
    }
    return 1;
}

/* One call's inputs and outputs (see pallet6d_icp), the boxes as structure of arrays, and the next pose to run. */
struct icp_job {
    int64_t n_poses, n_max, k, steps, min_inliers;
    const float *pts;
    const int64_t *n_pts;
    const double *T0, *prior, *stop_near;
    double corr_start_m, corr_end_m, tol, stop_near_m;
    float lo[3][MAX_BOXES], hi[3][MAX_BOXES];
    double model_lo[3], model_hi[3], corners[8][3];
    uint8_t all_boxes[MAX_BOXES];                          /* 0 .. k-1: the candidates outside the grid */
    /* optional grid over the model (pallet frame): the boxes that can be closest to a point of each cell */
    const double *grid_origin;
    double grid_inv_cell;
    const int64_t *grid_dims;
    const int32_t *grid_offsets;
    const uint8_t *grid_lists;
    double *T_out, *rms_out;
    int64_t *iters_out, *n_in_out;
    uint8_t *converged_out, *stopped_out;
    atomic_llong next;
};

/* ICP from pose i of the job. */
static void icp_one(struct icp_job *job, int64_t i) {
    const int64_t steps = job->steps, k = job->k, n_max = job->n_max, min_inliers = job->min_inliers;
    const double *model_lo = job->model_lo, *model_hi = job->model_hi;
    const double (*corners)[3] = (const double (*)[3])job->corners;
    const double *stop_near = job->stop_near, corr_start_m = job->corr_start_m, corr_end_m = job->corr_end_m;
    const double tol = job->tol, stop_near_m = job->stop_near_m;
    const float *pts = job->pts;
    const int64_t *n_pts = job->n_pts;
    const double *T0 = job->T0, *prior = job->prior;
    const float *P = pts + 3 * n_max * i;
    const double *pr = prior + 6 * i;
    double T_pal_cam[16], T_next[16], M[16], xi[6] = {0.0};
    double corners_cam[8][3];
    rigid_inverse(T0 + 16 * i, T_pal_cam);
    if (stop_near) {
        const double *S = stop_near + 16 * i;
        for (int c = 0; c < 8; c++)
            for (int r = 0; r < 3; r++)
                corners_cam[c][r] = S[4 * r] * corners[c][0] + S[4 * r + 1] * corners[c][1]
                                    + S[4 * r + 2] * corners[c][2] + S[4 * r + 3];
    }
    int64_t done = 0, n_in = 0;
    double rms = NAN;
    uint8_t converged = 0, stopped = 0;
    for (int64_t it = 0; it < steps; it++) {
        double thr = corr_start_m * pow(corr_end_m / corr_start_m, (double)it / (double)(steps > 1 ? steps - 1 : 1));
        float thr_f = (float)thr;
        float R[9], t[3];
        for (int r = 0; r < 3; r++) {
            for (int c = 0; c < 3; c++) R[3 * r + c] = (float)T_pal_cam[4 * r + c];
            t[r] = (float)T_pal_cam[4 * r + 3];
        }
        double H[36] = {0.0}, g[6] = {0.0}, wsum = 0.0, wrr = 0.0;
        int64_t n_use = 0;
        for (int64_t j = 0; j < n_pts[i]; j++) {
            const float *o = P + 3 * j;
            float p[3];
            for (int r = 0; r < 3; r++) p[r] = R[3 * r] * o[0] + R[3 * r + 1] * o[1] + R[3 * r + 2] * o[2] + t[r];
            int near = 1;
            for (int a = 0; a < 3; a++)
                near &= (double)p[a] > model_lo[a] - thr && (double)p[a] < model_hi[a] + thr;
            if (!near) continue;
            const uint8_t *cand = job->all_boxes;
            int64_t n_cand = k;
            if (job->grid_lists) {
                int64_t c = 0, inside = 1;
                for (int a = 0; a < 3; a++) {          /* truncation is floor on [0, dims) (floor is a call) */
                    double x = ((double)p[a] - job->grid_origin[a]) * job->grid_inv_cell;
                    inside &= x >= 0.0 && x < (double)job->grid_dims[a];
                    c = c * job->grid_dims[a] + (inside ? (int64_t)x : 0);
                }
                if (inside) {
                    cand = job->grid_lists + job->grid_offsets[c];
                    n_cand = job->grid_offsets[c + 1] - job->grid_offsets[c];
                }
            }
            float q[3], nrm[3], d;
            closest_on_boxes(p, job->lo, job->hi, cand, n_cand, q, nrm, &d);
            if (!(d < thr_f)) continue;                 /* in float32, as numpy compares float32 with a float */
            n_use++;
            float u = minf(d, thr_f) / thr_f, w = (1.0f - u * u) * (1.0f - u * u);   /* Tukey biweight */
            float res = (p[0] - q[0]) * nrm[0] + (p[1] - q[1]) * nrm[1] + (p[2] - q[2]) * nrm[2];
            double J[6] = {p[1] * nrm[2] - p[2] * nrm[1], p[2] * nrm[0] - p[0] * nrm[2],
                           p[0] * nrm[1] - p[1] * nrm[0], nrm[0], nrm[1], nrm[2]};
            for (int r = 0; r < 6; r++) {
                double wj = w * J[r];
                for (int c = 0; c <= r; c++) H[6 * r + c] += wj * J[c];
                g[r] += wj * res;
            }
            wsum += w;
            wrr += (double)(w * res * res);
        }
        if (n_use < min_inliers || !(wsum > 0.0)) break;      /* too few matches: keep the pose so far */
        double var = fmax(wrr / wsum, 0.002 * 0.002);         /* the data's noise, metres^2 */
        double delta[6];
        for (int r = 0; r < 6; r++) {
            for (int c = 0; c <= r; c++) H[6 * r + c] = H[6 * c + r] = H[6 * r + c] / var;
            H[6 * r + r] += pr[r];
            g[r] = g[r] / var + xi[r] * pr[r];
        }
        if (!solve6(H, g, delta)) break;
        double moved = 0.0;
        for (int r = 0; r < 6; r++) {
            delta[r] = -delta[r];
            xi[r] += delta[r];
            moved += fabs(delta[r]);
        }
        exp_se3(delta, M);
        mat4_mul(M, T_pal_cam, T_next);
        memcpy(T_pal_cam, T_next, sizeof T_pal_cam);
        n_in = n_use;
        rms = sqrt(wrr / wsum);
        done = it + 1;
        converged = moved < tol && it >= steps / 2;
        if (stop_near) {
            /* stop_near's corners taken into this pose's pallet frame come back unmoved when the poses agree */
            double worst = 0.0;
            for (int c = 0; c < 8; c++) {
                double e2 = 0.0;
                for (int r = 0; r < 3; r++) {
                    const double *Tr = T_pal_cam + 4 * r;
                    double h = Tr[0] * corners_cam[c][0] + Tr[1] * corners_cam[c][1] + Tr[2] * corners_cam[c][2]
                               + Tr[3] - corners[c][r];
                    e2 += h * h;
                }
                worst = fmax(worst, sqrt(e2));
            }
            stopped = worst < stop_near_m;
        }
        if (converged || stopped) break;
    }
    if (done > 0)
        rigid_inverse(T_pal_cam, job->T_out + 16 * i);
    else                                                    /* never stepped: the input pose, exactly */
        memcpy(job->T_out + 16 * i, T0 + 16 * i, 16 * sizeof(double));
    job->iters_out[i] = done;
    job->n_in_out[i] = n_in;
    job->rms_out[i] = rms;
    job->converged_out[i] = converged;
    job->stopped_out[i] = stopped;
}

/* worker(job) on the calling thread and on up to n_threads - 1 more, one per chunk of `chunk` of the P poses at
   most; the workers take chunks until none is left (a thread that cannot be started leaves its share to the
   others). */
static void run_shared(void *(*worker)(void *), void *job, int64_t P, int64_t chunk, int64_t n_threads) {
    enum { MAX_THREADS = 16 };
    int64_t extra = (n_threads < (P + chunk - 1) / chunk ? n_threads : (P + chunk - 1) / chunk) - 1;
    extra = extra < 0 ? 0 : extra > MAX_THREADS - 1 ? MAX_THREADS - 1 : extra;
    pthread_t threads[MAX_THREADS];
    int started[MAX_THREADS] = {0};
    for (int64_t t = 0; t < extra; t++) started[t] = pthread_create(&threads[t], NULL, worker, job) == 0;
    worker(job);
    for (int64_t t = 0; t < extra; t++)
        if (started[t]) pthread_join(threads[t], NULL);
}

/* Poses taken one at a time until none is left (the threads share the job). */
static void *icp_worker(void *arg) {
    struct icp_job *job = arg;
    for (int64_t i = atomic_fetch_add(&job->next, 1); i < job->n_poses; i = atomic_fetch_add(&job->next, 1))
        icp_one(job, i);
    return NULL;
}

/* ICP for n_poses starting poses, each on its own points, on up to n_threads threads (poses are independent).

   pts: (n_poses, n_max, 3) float, camera frame, metres; pose i uses its first n_pts[i] rows.
   boxes: (k, 2, 3) double min/max corners, pallet frame. T0, stop_near: (n_poses, 4, 4) pallet -> camera
   (stop_near may be NULL). prior: (n_poses, 6) inverse variances of the prior (rotation, translation).
   Outputs per pose: T_out (4, 4) pallet -> camera, steps run, inliers and weighted RMS of the last step
   (NaN when it never stepped), converged and stopped-near flags.
   grid (optional, NULL grid_lists for none): origin (3,) and cell size of a grid over the boxes, pallet frame,
   dims (3,), and per cell (x-major) the ascending indices of the boxes that can be closest to a point in it:
   lists[offsets[c] .. offsets[c + 1]) (kernels.box_grid); points outside it are measured against every box.
   Returns 0, or -1 when k is out of range (the caller validates everything else). A thread that cannot be
   started leaves its share to the others. */
int pallet6d_icp(int64_t n_poses, int64_t n_max, const float *pts, const int64_t *n_pts, int64_t k,
                 const double *boxes, const double *T0, const double *prior, int64_t iterations,
                 double corr_start_m, double corr_end_m, int64_t min_inliers, double tol,
                 const double *stop_near, double stop_near_m, const double *grid_origin, double grid_cell_m,
                 const int64_t *grid_dims, const int32_t *grid_offsets, const uint8_t *grid_lists,
                 int64_t n_threads, double *T_out, int64_t *iters_out,
                 int64_t *n_in_out, double *rms_out, uint8_t *converged_out, uint8_t *stopped_out) {
    if (k < 1 || k > MAX_BOXES) return -1;
    struct icp_job *job = calloc(1, sizeof *job);
    if (job == NULL) return -2;
    job->n_poses = n_poses, job->n_max = n_max, job->k = k, job->steps = iterations > 0 ? iterations : 0;
    job->min_inliers = min_inliers, job->pts = pts, job->n_pts = n_pts, job->T0 = T0, job->prior = prior;
    job->stop_near = stop_near, job->corr_start_m = corr_start_m, job->corr_end_m = corr_end_m, job->tol = tol;
    job->stop_near_m = stop_near_m;
    if (grid_lists != NULL && grid_cell_m > 0.0) {
        job->grid_origin = grid_origin, job->grid_inv_cell = 1.0 / grid_cell_m, job->grid_dims = grid_dims;
        job->grid_offsets = grid_offsets, job->grid_lists = grid_lists;
    }
    for (int64_t b = 0; b < k; b++) job->all_boxes[b] = (uint8_t)b;
    job->T_out = T_out, job->rms_out = rms_out, job->iters_out = iters_out, job->n_in_out = n_in_out;
    job->converged_out = converged_out, job->stopped_out = stopped_out;
    atomic_init(&job->next, 0);
    for (int a = 0; a < 3; a++) job->model_lo[a] = INFINITY, job->model_hi[a] = -INFINITY;
    for (int64_t b = 0; b < k; b++)
        for (int a = 0; a < 3; a++) {
            job->lo[a][b] = (float)boxes[6 * b + a];
            job->hi[a][b] = (float)boxes[6 * b + 3 + a];
            job->model_lo[a] = fmin(job->model_lo[a], boxes[6 * b + a]);
            job->model_hi[a] = fmax(job->model_hi[a], boxes[6 * b + 3 + a]);
        }
    for (int c = 0; c < 8; c++)
        for (int a = 0; a < 3; a++) job->corners[c][a] = (c >> a) & 1 ? job->model_hi[a] : job->model_lo[a];

    run_shared(icp_worker, job, n_poses, 1, n_threads);
    free(job);
    return 0;
}

/* ---- fit scores ------------------------------------------------------------------------------------------ */

/* Distance from p to a solid union of boxes (0 inside), as fit.distance_to_boxes. */
static double distance_to_boxes(const double p[3], const double *boxes, int64_t k) {
    double best = INFINITY;
    for (int64_t b = 0; b < k; b++) {
        const double *lo = boxes + 6 * b, *hi = lo + 3;
        double d2 = 0.0;
        for (int a = 0; a < 3; a++) {
            double g = lo[a] - p[a], g2 = p[a] - hi[a];
            g = g > g2 ? g : g2;
            g = g > 0.0 ? g : 0.0;
            d2 += g * g;
        }
        best = d2 < best ? d2 : best;
    }
    return sqrt(best);
}

/* The fit score's inputs (see pallet6d_fit). */
struct fit_model {
    int64_t m, k, k_in;
    const double *points, *boxes, *in_boxes, *lo, *hi;
    const double *idx_origin, *idx_points;            /* ModelPointIndex: the points in cell c are */
    double idx_cell;                                   /* idx_points[idx_offsets[c] : idx_offsets[c + 1]] */
    const int64_t *idx_shape, *idx_offsets;
};

/* Whether model-frame point p is within tol of the model (fit_scores' inlier test, same branches). */
static int is_inlier(const struct fit_model *f, const double p[3], double tol) {
    double d2 = 0.0;
    for (int a = 0; a < 3; a++) {
        double g = f->lo[a] - p[a], g2 = p[a] - f->hi[a];
        g = g > g2 ? g : g2;
        g = g > 0.0 ? g : 0.0;
        d2 += g * g;
    }
    if (!(d2 <= (tol + 1e-6) * (tol + 1e-6))) return 0;  /* beyond the model's bounding box */
    if (f->boxes) return distance_to_boxes(p, f->boxes, f->k) <= tol;
    if (f->in_boxes && !(distance_to_boxes(p, f->in_boxes, f->k_in) <= tol + 1e-6)) return 0;
    double best = INFINITY;
    if (f->idx_points) {
        int64_t lo[3], hi[3];
        for (int a = 0; a < 3; a++) {
            double x = floor((p[a] - f->idx_origin[a]) / f->idx_cell);
            if (!(x >= 0.0 && x < (double)f->idx_shape[a])) return 0;   /* outside the index: no point within */
            lo[a] = (int64_t)x > 0 ? (int64_t)x - 1 : 0;                 /* the cell and its neighbours */
            hi[a] = (int64_t)x + 1 < f->idx_shape[a] ? (int64_t)x + 1 : f->idx_shape[a] - 1;
        }
        for (int64_t cx = lo[0]; cx <= hi[0]; cx++)
            for (int64_t cy = lo[1]; cy <= hi[1]; cy++)
                for (int64_t cz = lo[2]; cz <= hi[2]; cz++) {
                    const int64_t c = (cx * f->idx_shape[1] + cy) * f->idx_shape[2] + cz;
                    for (int64_t j = f->idx_offsets[c]; j < f->idx_offsets[c + 1]; j++) {
                        double e2 = 0.0;
                        for (int a = 0; a < 3; a++) {
                            double e = f->idx_points[3 * j + a] - p[a];
                            e2 += e * e;
                        }
                        best = e2 < best ? e2 : best;
                    }
                }
    } else {
        for (int64_t j = 0; j < f->m; j++) {
            double e2 = 0.0;
            for (int a = 0; a < 3; a++) {
                double e = f->points[3 * j + a] - p[a];
                e2 += e * e;
            }
            best = e2 < best ? e2 : best;
        }
    }
    return sqrt(best) <= tol;
}

/* Fit scores of P poses (fit.fit_scores): the fraction of each pose's observed points within tol of the posed
   model, and the fraction of the model's camera-facing points (a z-buffer of the model on cell_px cells) that
   lie more than tol in front of valid depth.

   obs: (P, N, 3) camera frame, pose i uses its first n_obs[i]; T: (P, 4, 4) model -> camera; model points (m, 3);
   lo, hi: (3,) the box around the model for the inlier pre-test; boxes (k, 2, 3): distances to the boxes, or NULL
   for distances to the points (in_boxes (k_in, 2, 3) or NULL: a pre-test; the index arrays or NULL idx_points: a
   search over all points); depth (H, W) float metres, 0 = no data; K (3, 3).
   Returns 0, or -2 when a z-buffer cannot be allocated. */
int pallet6d_fit(int64_t P, int64_t N, const double *obs, const int64_t *n_obs, const double *T, int64_t m,
                 const double *points, const double *lo, const double *hi, int64_t k, const double *boxes,
                 int64_t k_in, const double *in_boxes, const double *idx_origin, double idx_cell,
                 const int64_t *idx_shape, const int64_t *idx_offsets, const double *idx_points,
                 const float *depth, int64_t H, int64_t W, const double *K, double tol, int64_t cell_px,
                 double *inlier_out, double *violation_out) {
    struct fit_model f = {m, k, k_in, points, boxes, in_boxes, lo, hi, idx_origin, idx_points, idx_cell, idx_shape,
                          idx_offsets};
    const int64_t cells_w = (W + cell_px - 1) / cell_px;
    int64_t *uv = malloc((size_t)(m > 0 ? m : 1) * 2 * sizeof(int64_t));
    double *zs = malloc((size_t)(m > 0 ? m : 1) * sizeof(double));
    int64_t *row_cell = malloc((size_t)(H + W > 0 ? H + W : 1) * sizeof(int64_t)), *col_cell = row_cell + H;
    if (uv == NULL || zs == NULL || row_cell == NULL) { free(uv); free(zs); free(row_cell); return -2; }
    for (int64_t v = 0; v < H; v++) row_cell[v] = (v / cell_px) * cells_w;   /* a pixel's cell: no division per point */
    for (int64_t u = 0; u < W; u++) col_cell[u] = u / cell_px;
    int rc = 0;
    for (int64_t i = 0; i < P && rc == 0; i++) {
        const double *Ti = T + 16 * i;
        /* inliers: observed points in the model frame, R^T (p - t) */
        int64_t n_in = 0;
        for (int64_t j = 0; j < n_obs[i]; j++) {
            const double *o = obs + 3 * (N * i + j);
            double d[3] = {o[0] - Ti[3], o[1] - Ti[7], o[2] - Ti[11]}, p[3];
            for (int a = 0; a < 3; a++) p[a] = d[0] * Ti[a] + d[1] * Ti[4 + a] + d[2] * Ti[8 + a];
            n_in += is_inlier(&f, p, tol);
        }
        inlier_out[i] = n_obs[i] > 0 ? (double)n_in / (double)n_obs[i] : 0.0;
        /* free space: project the posed model, keep the pixels inside the image */
        int64_t n = 0, cell_lo = INT64_MAX, cell_hi = -1;
        for (int64_t j = 0; j < m; j++) {
            const double *q = points + 3 * j;
            double c[3];
            for (int r = 0; r < 3; r++)
                c[r] = Ti[4 * r] * q[0] + Ti[4 * r + 1] * q[1] + Ti[4 * r + 2] * q[2] + Ti[4 * r + 3];
            if (!(c[2] > 1e-6)) continue;
            double u = round_even(c[0] * K[0] / c[2] + K[2]), v = round_even(c[1] * K[4] / c[2] + K[5]);
            if (!(u >= 0.0 && u < (double)W && v >= 0.0 && v < (double)H)) continue;
            /* uv: the point's pixel (row-major index) and its z-buffer cell, each found once */
            const int64_t iu = (int64_t)u, iv = (int64_t)v, cell = row_cell[iv] + col_cell[iu];
            uv[2 * n] = iv * W + iu, uv[2 * n + 1] = cell, zs[n] = c[2];
            cell_lo = cell < cell_lo ? cell : cell_lo;
            cell_hi = cell > cell_hi ? cell : cell_hi;
            n++;
        }
        if (n == 0) { violation_out[i] = 0.0; continue; }
        int64_t span = cell_hi - cell_lo + 1;
        double *z_near = malloc((size_t)span * sizeof(double));
        if (z_near == NULL) { rc = -2; break; }
        for (int64_t c = 0; c < span; c++) z_near[c] = INFINITY;
        for (int64_t j = 0; j < n; j++) {
            const int64_t c = uv[2 * j + 1] - cell_lo;
            z_near[c] = zs[j] < z_near[c] ? zs[j] : z_near[c];
        }
        int64_t n_use = 0, n_bad = 0;
        for (int64_t j = 0; j < n; j++) {
            const float d_obs = depth[uv[2 * j]];
            if (zs[j] <= z_near[uv[2 * j + 1] - cell_lo] + tol && d_obs > 0.0f) {
                n_use++;
                n_bad += zs[j] < (double)(d_obs - (float)tol);   /* float32, as numpy subtracts from float32 depth */
            }
        }
        free(z_near);
        violation_out[i] = n_use > 0 ? (double)n_bad / (double)n_use : 0.0;
    }
    free(uv);
    free(zs);
    free(row_cell);
    return rc;
}

/* ---- the registration test's pair counts ------------------------------------------------------------------- */

/* Histograms of the colour differences of pairs whose depth jumps (pos) and of the other pairs (neg), with the
   depth read at the image's grid pixels shifted by (dy, dx) (registration.registration_score's `auc`).

   pad: (pad_h, pad_w) float metres around the grid, 0 = no data, the grid's pixel (iy, ix) at pad row
   m + iy * step, column m + ix * step; inside, diff_x, diff_y: (ny, nx) the grid's mask and the colour differences
   of the pairs along x and y (integers in [0, levels)); a: pixels between a pair's two pixels. Float arithmetic as
   numpy's on float32 depth. pos, neg: (levels,) counts, added to. Returns 0, or -1 when a read would leave pad or a
   difference is out of range. */
int pallet6d_registration_counts(const float *pad, int64_t pad_h, int64_t pad_w, int64_t m, int64_t step,
                                 int64_t ny, int64_t nx, const uint8_t *inside, const int64_t *diff_x,
                                 const int64_t *diff_y, int64_t a, int64_t dy, int64_t dx, double tol_m,
                                 double tol_quad_per_m, int64_t levels, int64_t *pos, int64_t *neg) {
    const float tol = (float)tol_m, quad = (float)tol_quad_per_m;
    for (int dir = 0; dir < 2; dir++) {
        const int64_t ey = dir, ex = 1 - dir;
        const int64_t *diff = dir == 0 ? diff_x : diff_y;
        /* the four reads of a pair: before it, its two pixels, after it */
        int64_t off[4];
        for (int k = 0; k < 4; k++) {
            int64_t ry = m + dy + (k - 1) * a * ey, rx = m + dx + (k - 1) * a * ex;
            if (ry < 0 || rx < 0 || ry + (ny - 1) * step >= pad_h || rx + (nx - 1) * step >= pad_w) return -1;
            off[k] = ry * pad_w + rx;
        }
        for (int64_t iy = 0; iy < ny; iy++)
            for (int64_t ix = 0; ix < nx; ix++) {
                if (!inside[iy * nx + ix]) continue;
                const int64_t at = iy * step * pad_w + ix * step;
                const float z_b = pad[off[0] + at], z0 = pad[off[1] + at];
                const float z1 = pad[off[2] + at], z_a = pad[off[3] + at];
                if (!(z0 > 0.0f && z1 > 0.0f)) continue;
                const float far = z0 > z1 ? z0 : z1, step_m = fabsf(z0 - z1);
                const int jump = step_m > 2.0f * (tol + quad * far * far);
                /* a surface's end is a step between flatter flanks; a noise spike changes as much beside it */
                const int flat = fabsf(z_b - z0) < 0.5f * step_m && fabsf(z_a - z1) < 0.5f * step_m;
                if (jump && !flat) continue;
                const int64_t d = diff[iy * nx + ix];
                if (d < 0 || d >= levels) return -1;
                (jump ? pos : neg)[d]++;
            }
    }
    return 0;
}

/* ---- ray scores of posed pallets ---------------------------------------------------------------------------- */

/* The boxes' bounding box: blo, bhi (3,) from (k, 2, 3) min / max corners. */
static void boxes_bounds(const double *boxes, int64_t k, double blo[3], double bhi[3]) {
    for (int r = 0; r < 3; r++) {
        blo[r] = INFINITY;
        bhi[r] = -INFINITY;
    }
    for (int64_t b = 0; b < k; b++)
        for (int r = 0; r < 3; r++) {
            blo[r] = boxes[6 * b + r] < blo[r] ? boxes[6 * b + r] : blo[r];
            bhi[r] = boxes[6 * b + 3 + r] > bhi[r] ? boxes[6 * b + 3 + r] : bhi[r];
        }
}

/* The camera -> pallet rotation R_pc (row-major 3x3) and the camera's position o in the pallet frame of the
   pallet -> camera transform T (row-major 4x4). */
static void camera_in_pallet(const double *T, double R_pc[9], double o[3]) {
    for (int r = 0; r < 3; r++)
        for (int c = 0; c < 3; c++) R_pc[3 * r + c] = T[4 * c + r];
    for (int r = 0; r < 3; r++) o[r] = -(R_pc[3 * r] * T[3] + R_pc[3 * r + 1] * T[7] + R_pc[3 * r + 2] * T[11]);
}

/* The boxes in the order of their distance from the camera o (pallet frame), nearest first: order[j] the box,
   dist[j] its distance (0 for a box holding o). A ray whose point is at |d| per unit of s enters box order[j] no
   earlier than s = dist[j] / |d|, so first_hit stops at the first box that cannot be met before the nearest hit so
   far: most rays meet a front board among the first few boxes. k <= MAX_BOXES. */
static void order_boxes(const double o[3], const double *boxes, int64_t k, int64_t *order, double *dist) {
    for (int64_t b = 0; b < k; b++) {
        double d2 = 0.0;
        for (int r = 0; r < 3; r++) {
            const double lo = boxes[6 * b + r] - o[r], hi = o[r] - boxes[6 * b + 3 + r];
            const double g = lo > 0 ? lo : hi > 0 ? hi : 0.0;
            d2 += g * g;
        }
        const double d = sqrt(d2);
        int64_t j = b;
        for (; j > 0 && dist[j - 1] > d; j--) {            /* insertion sort: a few dozen boxes */
            dist[j] = dist[j - 1];
            order[j] = order[j - 1];
        }
        dist[j] = d;
        order[j] = b;
    }
}

/* One pose's boxes as its rays meet them: the camera o (pallet frame) taken off every corner, the boxes in
   `order_boxes`' order (nearest first, dist[j] each), and their bounding box's corners the same way. The slab tests
   then read (corner - o) ready made: the same doubles as computing them per ray. */
struct posed_boxes {
    double rel[MAX_BOXES][6], dist[MAX_BOXES], blo[3], bhi[3];
    int64_t k;
};

static void pose_boxes(const double o[3], const double *boxes, int64_t k, const double blo[3], const double bhi[3],
                       struct posed_boxes *pb) {
    int64_t order[MAX_BOXES];
    order_boxes(o, boxes, k, order, pb->dist);
    for (int64_t j = 0; j < k; j++)
        for (int r = 0; r < 6; r++) pb->rel[j][r] = boxes[6 * order[j] + r] - o[r % 3];
    for (int r = 0; r < 3; r++) {
        pb->blo[r] = blo[r] - o[r];
        pb->bhi[r] = bhi[r] - o[r];
    }
    pb->k = k;
}

/* Slab test of the ray from the origin along d (inv = 1 / d per axis) against the box whose corners, taken relative
   to the ray's origin, are rlo..rhi: 1 when it meets it at some s > 0, with *entry the first such s (0 when the
   origin is inside). */
static inline int ray_box(const double inv[3], const double rlo[3], const double rhi[3], double *entry) {
    double near = -INFINITY, far = INFINITY;
    for (int r = 0; r < 3; r++) {
        const double t1 = rlo[r] * inv[r], t2 = rhi[r] * inv[r];
        const double a = t1 < t2 ? t1 : t2, z = t1 < t2 ? t2 : t1;
        near = a > near ? a : near;
        far = z < far ? z : far;
    }
    *entry = near > 0 ? near : 0.0;
    return near <= far && far > 0;
}

/* The first s > 0 at which the ray from the pose's camera along d meets one of its boxes, looking only below s_max
   (INFINITY: everywhere) and ending at the first hit found at s <= s_beyond (-INFINITY: never); INFINITY when
   there is none. *entry: where the ray enters the boxes' bounding box (0 when it starts inside), INFINITY when it
   misses it (then it misses every box). The boxes are tried nearest first until none can be met earlier (a small
   margin keeps rounding from skipping a box): the same s as trying all of them. */
static double first_hit(const double d[3], const struct posed_boxes *pb, double s_max, double s_beyond,
                        double *entry) {
    double inv[3], e, d2 = 0.0;
    for (int r = 0; r < 3; r++) {
        inv[r] = fabs(d[r]) > 1e-12 ? 1.0 / d[r] : 1e12;
        d2 += d[r] * d[r];
    }
    if (!ray_box(inv, pb->blo, pb->bhi, entry)) {
        *entry = INFINITY;
        return INFINITY;
    }
    if (*entry >= s_max) return INFINITY;
    const double reach = sqrt(d2) * (1.0 + 1e-9) + 1e-12;   /* distance per unit of s, rounded up */
    double s = s_max;
    for (int64_t j = 0; j < pb->k && pb->dist[j] <= s * reach; j++)
        if (ray_box(inv, pb->rel[j], pb->rel[j] + 3, &e) && e < s) {
            s = e;
            if (s <= s_beyond) return s;
        }
    return s < s_max ? s : INFINITY;
}

/* `first_hit` of the ray from the camera through the camera-frame point p (s = 1 at p; R_pc: camera -> pallet), for a
   caller that needs the point's residual (1 - s) * |p| only where it lies within window_m of the surface, and
   otherwise only whether it lies beyond it (residual >= window_m; rng = |p|): the search ends at the first hit found
   that puts the point beyond the window (any earlier hit would put it further beyond), and looks for hits only up
   to s_max = 1 + window_m / |p| and a little (a first hit past that leaves the point in front of the surface by more
   than the window, or no hit at all: INFINITY, which counts as neither). The callers classify every point as they
   would with the first hit of all. */
static double first_hit_window(const double R_pc[9], const double *p, double rng, double window_m,
                               const struct posed_boxes *pb) {
    double d[3], entry;
    for (int r = 0; r < 3; r++) d[r] = R_pc[3 * r] * p[0] + R_pc[3 * r + 1] * p[1] + R_pc[3 * r + 2] * p[2];
    const double margin = window_m / rng * (1.0 + 1e-9);        /* 1e-9: well above the residual's rounding */
    return first_hit(d, pb, 1.0 + margin, 1.0 - margin, &entry);
}

/* What level._along_rays needs of P poses' points (its numpy path is the specification): each point's viewing ray
   meets the posed boxes first at s times the point's distance; its residual (1 - s) * |p| is its depth beyond the
   model's surface. Per pose i, of its first n_pts[i] points (T: (P, 4, 4) pallet -> camera; pts: (P, N, 3) camera
   frame; boxes: (k, 2, 3), pallet frame, k <= MAX_BOXES), those with |residual| < window_m: count_out[i], the median
   of their residuals shift_out[i] (the mean of the two middle ones for an even count; 0 for none) and the sum of
   their unit viewing directions ray_out[i] (3,). scratch: (P, N) doubles, row i pose i's work area. The poses are
   shared among up to n_threads threads, 4 at a time (a thread that cannot be started leaves its share to the
   others). Returns 0, or 1 (nothing written) for more than MAX_BOXES boxes. */
struct along_rays_job {
    const double *T, *pts, *boxes, *blo, *bhi;
    const int64_t *n_pts;
    int64_t P, N, k, chunk;
    double window_m, *scratch, *shift_out, *ray_out;
    int64_t *count_out;
    atomic_long next;
};

static int cmp_double(const void *a, const void *b) {
    const double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static void *along_rays_worker(void *arg) {
    struct along_rays_job *job = arg;
    for (int64_t i0 = atomic_fetch_add(&job->next, job->chunk); i0 < job->P;
         i0 = atomic_fetch_add(&job->next, job->chunk))
        for (int64_t i = i0; i < i0 + job->chunk && i < job->P; i++) {
            double R_pc[9], o[3], ray[3] = {0.0, 0.0, 0.0};
            struct posed_boxes pb;
            int64_t c = 0;
            double *res = job->scratch + i * job->N;
            camera_in_pallet(job->T + 16 * i, R_pc, o);
            pose_boxes(o, job->boxes, job->k, job->blo, job->bhi, &pb);
            const int64_t n = job->n_pts[i] < job->N ? job->n_pts[i] : job->N;
            for (int64_t j = 0; j < n; j++) {
                const double *p = job->pts + 3 * (i * job->N + j);
                const double rng = sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
                const double s = first_hit_window(R_pc, p, rng, job->window_m, &pb);
                if (!isfinite(s)) continue;
                const double r = (1.0 - s) * rng;
                if (!(fabs(r) < job->window_m)) continue;
                res[c++] = r;
                for (int a = 0; a < 3; a++) ray[a] += p[a] / rng;
            }
            double median = 0.0;
            if (c > 0) {
                qsort(res, (size_t)c, sizeof(double), cmp_double);
                median = 0.5 * (res[(c - 1) / 2] + res[c / 2]);
            }
            job->count_out[i] = c;
            job->shift_out[i] = median;
            for (int a = 0; a < 3; a++) job->ray_out[3 * i + a] = ray[a];
        }
    return NULL;
}

int pallet6d_along_rays(int64_t P, const double *T, int64_t N, const double *pts, const int64_t *n_pts, int64_t k,
                        const double *boxes, double window_m, int64_t n_threads, double *scratch, int64_t *count_out,
                        double *shift_out, double *ray_out) {
    if (k > MAX_BOXES) return 1;
    double blo[3], bhi[3];
    boxes_bounds(boxes, k, blo, bhi);
    struct along_rays_job job = {.T = T, .pts = pts, .boxes = boxes, .blo = blo, .bhi = bhi, .n_pts = n_pts, .P = P,
                                 .N = N, .k = k, .chunk = 4, .window_m = window_m, .scratch = scratch,
                                 .shift_out = shift_out, .ray_out = ray_out, .count_out = count_out};
    atomic_init(&job.next, 0);
    run_shared(along_rays_worker, &job, P, job.chunk, n_threads);
    return 0;
}

/* The structure check's rays (structure.cast_rays_boxes is the specification), for P poses that may each have
   their own pallet type: ray j of pose i is origin[i] + s dirs[i, j] (pallet frame), s > 0. t_box[i * R + j] = s of
   its first hit with the pose's boxes (boxes[box_start[i] : box_start[i] + box_count[i]], min / max corners),
   INFINITY when none; t_bbox[i * R + j] = s where it enters their bounding box (0 when it starts inside), INFINITY
   when it misses it. Double arithmetic, as numpy's. Returns 0, or 1 (nothing written) when a pose has no box or
   more than MAX_BOXES (kernels.py checks the starts and counts against the boxes given). */
int pallet6d_cast_rays(int64_t P, int64_t R, const double *origin, const double *dirs, const int64_t *box_start,
                       const int64_t *box_count, const double *boxes, double *t_box, double *t_bbox) {
    for (int64_t i = 0; i < P; i++)
        if (box_count[i] < 1 || box_count[i] > MAX_BOXES) return 1;
    struct posed_boxes pb;
    for (int64_t i = 0; i < P; i++) {
        const double *b = boxes + 6 * box_start[i];
        double blo[3], bhi[3];
        boxes_bounds(b, box_count[i], blo, bhi);
        pose_boxes(origin + 3 * i, b, box_count[i], blo, bhi, &pb);
        for (int64_t j = 0; j < R; j++)
            t_box[i * R + j] = first_hit(dirs + 3 * (i * R + j), &pb, INFINITY, -INFINITY, &t_bbox[i * R + j]);
    }
    return 0;
}

/* How well each of P poses explains m observed points along their viewing rays (level.ray_scores' numpy path is the
   specification): the ray from the camera to each point meets the posed model's boxes first at s times the
   point's distance (s = 1: at the point); its residual (1 - s) * |p| is the point's depth beyond the model's
   surface. out[i] = (points within window_m of the surface - points beyond it by window_m or more) / m; a ray
   that misses the model counts neither way. With soft != 0, out[i] = the sum of 1 - (res / window_m)^2 over the
   points within the window, / m: a score that peaks at the pose that explains the depth best instead of being flat
   within the window, and that noise along the rays does not push either way (no penalty beyond).
   T: (P, 4, 4) pallet -> camera; pts: (m, 3) camera frame; boxes: (k, 2, 3) min / max corners, pallet frame.
   Double arithmetic, as numpy's. The poses are shared among up to n_threads threads, 8 at a time (a thread that
   cannot be started leaves its share to the others). Returns 0, or 1 (nothing written) for more than MAX_BOXES
   boxes. */
struct ray_score_job {
    const double *T, *pts, *boxes, *blo, *bhi;
    int64_t P, m, k, chunk, soft;
    double window_m, *out;
    atomic_long next;
};

/* Chunks of poses taken one at a time until none is left (the threads share the job). */
static void *ray_score_worker(void *arg) {
    struct ray_score_job *job = arg;
    for (int64_t i0 = atomic_fetch_add(&job->next, job->chunk); i0 < job->P;
         i0 = atomic_fetch_add(&job->next, job->chunk))
        for (int64_t i = i0; i < i0 + job->chunk && i < job->P; i++) {
            double R_pc[9], o[3];
            struct posed_boxes pb;
            camera_in_pallet(job->T + 16 * i, R_pc, o);
            pose_boxes(o, job->boxes, job->k, job->blo, job->bhi, &pb);
            double inl = 0.0;
            int64_t beyond = 0;
            for (int64_t j = 0; j < job->m; j++) {
                const double *p = job->pts + 3 * j;
                const double rng = sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
                const double s = first_hit_window(R_pc, p, rng, job->window_m, &pb);
                if (!isfinite(s)) continue;
                const double res = (1.0 - s) * rng;
                if (fabs(res) < job->window_m) {
                    const double q = res / job->window_m;
                    inl += job->soft ? 1.0 - q * q : 1.0;
                } else if (res >= job->window_m && !job->soft)
                    beyond++;
            }
            job->out[i] = job->m > 0 ? (inl - (double)beyond) / (double)job->m : 0.0;
        }
    return NULL;
}

int pallet6d_ray_scores(int64_t P, const double *T, int64_t m, const double *pts, int64_t k, const double *boxes,
                        double window_m, int64_t soft, int64_t n_threads, double *out) {
    if (k > MAX_BOXES) return 1;
    double blo[3], bhi[3];
    boxes_bounds(boxes, k, blo, bhi);
    struct ray_score_job job = {.T = T, .pts = pts, .boxes = boxes, .blo = blo, .bhi = bhi, .P = P, .m = m, .k = k,
                                .chunk = 8, .soft = soft, .window_m = window_m, .out = out};
    atomic_init(&job.next, 0);
    run_shared(ray_score_worker, &job, P, job.chunk, n_threads);
    return 0;
}
