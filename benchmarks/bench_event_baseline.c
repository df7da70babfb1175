/* Baseline of the rk4_event kernel for `afm_study bench`: afm_ros/core/physics/events.py `advance_event`
 * (flat sample, thermal force off, no sample recording) translated to C with the same floating-point
 * operations in the same order, so that the final (z, v), the energies and the stats are bit-identical
 * to numba's. Compiled at benchmark time with
 *     gcc -O2 -fno-fast-math -ffp-contract=off -shared -fPIC
 * (numba/LLVM neither reassociates nor contracts a * b + c into an fma) and called via ctypes.
 *
 * Python semantics kept: max(a, b) is (b > a ? b : a) and min(a, b) is (b < a ? b : a) (numba's
 * lowering), int / int is a true division of the two converted to double, int(math.ceil(x)) truncates
 * the ceiling, -a * b is (-a) * b, sums and products associate to the left.
 *
 * Structure as in numba: the plain RK4 step (with its energies) and the far-from-the-surface test are
 * inlined in the loop; the test near the surface (_near_step_stands) and the full path (event_step_full)
 * are separate functions that are not inlined, as numba compiles them (njit without inline="always").
 * The thermal force is the constant -0.0 added where numba adds fth: x + (-0.0) == x for every x, so the
 * compiler may drop the adds, as LLVM does in numba (x + 0.0 could not be dropped: -0.0 + 0.0 is +0.0).
 * The force constants are passed on by pointer (numba passes a tuple of them: no arithmetic difference).
 *
 * y = [z, v]; table has 2 spp + 1 entries (half-step drive); p = the packed force constants (6 values);
 * model 0 none, 1 dmt, 2 viscoelastic_dmt, 3 hysteresis_dmt; stats[0] += steps split at a switch,
 * stats[1] += RK4 sub-steps computed beyond one per step. out_w: NULL (no recording), else 4 rows of
 * nsteps values per step, what advance_event writes with decimation 1 (row stride nsteps): the energies
 * [J] taken by the tip-sample force, given by the drive, lost to damping, and the force's impulse [N s].
 */
#include <math.h>
#include <stddef.h>

#define MODEL_NONE 0
#define MODEL_DMT 1
#define MODEL_VISCOELASTIC_DMT 2
#define MODEL_HYSTERESIS_DMT 3

#define CONTACT 1
#define CLIPPED 2
#define RETRACT 4
#define ROOT_ITERATIONS 60
#define MAX_SWITCHES 4
#define MAX_PIECES 256
#define STIFF_PHASE 0.25

#define PI 3.141592653589793 /* math.pi */

static inline double py_max(double a, double b) { return b > a ? b : a; }
static inline double py_min(double a, double b) { return b < a ? b : a; }
static inline long py_max_long(long a, long b) { return b > a ? b : a; }
static inline long py_min_long(long a, long b) { return b < a ? b : a; }

/* forces.py tip_sample_force */
static inline double tip_sample_force(long model, const double *p, double gap, double rate)
{
    if (model == MODEL_DMT) {
        if (gap > p[0])
            return -p[1] / (gap * gap);
        double delta = p[0] - gap;
        return -p[3] + p[2] * delta * sqrt(delta);
    }
    if (model == MODEL_VISCOELASTIC_DMT) {
        if (gap > p[0])
            return -p[1] / (gap * gap);
        double delta = p[0] - gap;
        double root = sqrt(delta);
        double contact = p[2] * delta * root - p[4] * root * rate;
        return -p[3] + (contact > 0.0 ? contact : 0.0);
    }
    if (model == MODEL_HYSTERESIS_DMT) {
        double approach, retract;
        if (gap > p[0]) {
            approach = -p[1] / (gap * gap);
            retract = -p[4] / (gap * gap);
        } else {
            double delta = p[0] - gap;
            double hertz = p[2] * delta * sqrt(delta);
            approach = -p[3] + hertz;
            retract = -p[5] + hertz;
        }
        return rate >= 0.0 ? retract : approach;
    }
    return 0.0;
}

/* events.py region */
static inline int region(long model, const double *p, double gap, double rate)
{
    if (model == MODEL_NONE)
        return 0;
    int r = 0;
    if (gap <= p[0]) {
        r = CONTACT;
        if (model == MODEL_VISCOELASTIC_DMT && p[2] * (p[0] - gap) - p[4] * rate <= 0.0)
            r |= CLIPPED;
    }
    if (model == MODEL_HYSTERESIS_DMT && rate >= 0.0 && (p[4] != p[1] || p[5] != p[3]))
        r |= RETRACT;
    return r;
}

/* events.py force_in */
static inline double force_in(long model, const double *p, double gap, double rate, int r)
{
    if (model == MODEL_NONE)
        return 0.0;
    int retract = model == MODEL_HYSTERESIS_DMT && (r & RETRACT) != 0;
    if ((r & CONTACT) == 0) {
        double hr = retract ? p[4] : p[1];
        if (gap >= p[0])
            return -hr / (gap * gap);
        double u = (gap - p[0]) / p[0];
        return -hr / (p[0] * p[0]) * (1.0 - 2.0 * u + 3.0 * u * u);
    }
    double delta = p[0] - gap;
    if (delta < 0.0)
        delta = 0.0;
    double root = sqrt(delta);
    if (model == MODEL_VISCOELASTIC_DMT)
        return -p[3] + (((r & CLIPPED) != 0) ? 0.0 : p[2] * delta * root - p[4] * root * rate);
    return -(retract ? p[5] : p[3]) + p[2] * delta * root;
}

/* events.py _cos_sin */
static inline void cos_sin(double x, double *c, double *s)
{
    if (x > 0.16) {
        *c = cos(x);
        *s = sin(x);
        return;
    }
    double x2 = x * x;
    *c = 1.0 - x2 * 0.5 * (1.0 - x2 * (1.0 / 12.0) * (1.0 - x2 * (1.0 / 30.0) * (1.0 - x2 * (1.0 / 56.0)
                                                                                * (1.0 - x2 * (1.0 / 90.0)))));
    *s = x * (1.0 - x2 * (1.0 / 6.0) * (1.0 - x2 * (1.0 / 20.0) * (1.0 - x2 * (1.0 / 42.0)
                                                                 * (1.0 - x2 * (1.0 / 72.0)))));
}

/* events.py _drive */
static inline double drive_at(double d0, double ds0, double w_step, double theta)
{
    double cos_t, sin_t;
    cos_sin(w_step * theta, &cos_t, &sin_t);
    return d0 * cos_t - ds0 * sin_t;
}

typedef struct {
    double z, v, work, drive, damping, impulse;
} step_t;

/* events.py _rk4_in */
static inline step_t rk4_in(double z, double v, double fth, double d0, double dh, double d1, double k, double c,
                            double inv_m, long model, const double *p, double z_offset, double h, int r)
{
    double f1 = force_in(model, p, z_offset + z, v, r);
    double a1 = (-k * z - c * v + d0 + f1 + fth) * inv_m;
    double z2 = z + 0.5 * h * v;
    double v2 = v + 0.5 * h * a1;
    double f2 = force_in(model, p, z_offset + z2, v2, r);
    double a2 = (-k * z2 - c * v2 + dh + f2 + fth) * inv_m;
    double z3 = z + 0.5 * h * v2;
    double v3 = v + 0.5 * h * a2;
    double f3 = force_in(model, p, z_offset + z3, v3, r);
    double a3 = (-k * z3 - c * v3 + dh + f3 + fth) * inv_m;
    double z4 = z + h * v3;
    double v4 = v + h * a3;
    double f4 = force_in(model, p, z_offset + z4, v4, r);
    double a4 = (-k * z4 - c * v4 + d1 + f4 + fth) * inv_m;
    step_t out;
    out.work = -h / 6.0 * (f1 * v + 2.0 * (f2 * v2 + f3 * v3) + f4 * v4);
    out.drive = h / 6.0 * (d0 * v + 2.0 * dh * (v2 + v3) + d1 * v4);
    out.damping = h / 6.0 * c * (v * v + 2.0 * (v2 * v2 + v3 * v3) + v4 * v4);
    out.impulse = h / 6.0 * (f1 + 2.0 * (f2 + f3) + f4);
    out.z = z + h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4);
    out.v = v + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4);
    return out;
}

/* events.py _rk4_step_work (= integrators.py _rk4_step for z and v) */
static inline step_t rk4_step_work(double z, double v, double f1, double fth, double drive0, double drive_half,
                                   double drive1, double k, double c, double inv_m, long model, const double *fp,
                                   double z_offset, double h, double hh, double dt, double dth, double sixth,
                                   double dt_sixth)
{
    double a1 = (-k * z - c * v + drive0 + f1 + fth) * inv_m;
    double z2 = z + h * v;
    double v2 = v + h * a1;
    double f2 = tip_sample_force(model, fp, z_offset + z2, v2);
    double a2 = (-k * z2 - c * v2 + drive_half + f2 + fth) * inv_m;
    double z3 = z2 + hh * a1;
    double v3 = v + h * a2;
    double f3 = tip_sample_force(model, fp, z_offset + z3, v3);
    double a3 = (-k * z3 - c * v3 + drive_half + f3 + fth) * inv_m;
    double z_dt = z + dt * v;
    double z4 = z_dt + dth * a2;
    double v4 = v + dt * a3;
    double f4 = tip_sample_force(model, fp, z_offset + z4, v4);
    double a4 = (-k * z4 - c * v4 + drive1 + f4 + fth) * inv_m;
    step_t out;
    out.work = -sixth * (f1 * v + 2.0 * (f2 * v2 + f3 * v3) + f4 * v4);
    out.drive = sixth * (drive0 * v + 2.0 * drive_half * (v2 + v3) + drive1 * v4);
    out.damping = sixth * c * (v * v + 2.0 * (v2 * v2 + v3 * v3) + v4 * v4);
    out.impulse = sixth * (f1 + 2.0 * (f2 + f3) + f4);
    out.z = z_dt + dt_sixth * (a1 + a2 + a3);
    out.v = (v + sixth * (a1 + 2.0 * (a2 + a3))) + sixth * a4;
    return out;
}

/* events.py _hermite */
static inline void hermite(double z0, double v0, double z1, double v1, double h, double s, double *zo, double *vo)
{
    double s2 = s * s;
    double s3 = s2 * s;
    *zo = (2.0 * s3 - 3.0 * s2 + 1.0) * z0 + (s3 - 2.0 * s2 + s) * h * v0 + (-2.0 * s3 + 3.0 * s2) * z1
          + (s3 - s2) * h * v1;
    *vo = ((6.0 * s2 - 6.0 * s) * z0 + (3.0 * s2 - 4.0 * s + 1.0) * h * v0 + (-6.0 * s2 + 6.0 * s) * z1
           + (3.0 * s2 - 2.0 * s) * h * v1) / h;
}

/* events.py _turn */
static inline double turn(double z0, double v0, double z1, double v1, double h)
{
    if ((v0 > 0.0) == (v1 > 0.0) || v0 == 0.0)
        return -1.0;
    double a = 6.0 * z0 + 3.0 * h * v0 - 6.0 * z1 + 3.0 * h * v1;
    double b = -6.0 * z0 - 4.0 * h * v0 + 6.0 * z1 - 2.0 * h * v1;
    double c = h * v0;
    if (a == 0.0)
        return py_min(py_max(-c / b, 0.0), 1.0);
    double disc = sqrt(py_max(b * b - 4.0 * a * c, 0.0));
    double q = -0.5 * (b + copysign(disc, b));
    double r1 = q / a;
    double r2 = q != 0.0 ? c / q : r1;
    double s = (0.0 <= r1 && r1 <= 1.0) ? r1 : r2;
    return py_min(py_max(s, 0.0), 1.0);
}

/* events.py _other */
static inline double other(long model, const double *p, double z_offset, double z0, double v0, double z1, double v1,
                           double h, int r0)
{
    if (region(model, p, z_offset + z1, v1) != r0)
        return 1.0;
    double s = turn(z0, v0, z1, v1, h);
    if (s > 0.0) {
        double zt, vt;
        hermite(z0, v0, z1, v1, h, s, &zt, &vt);
        if ((region(model, p, z_offset + zt, 0.0) ^ r0) & CONTACT)
            return s;
    }
    return -1.0;
}

/* events.py _root */
static inline double root_in(double e0, double e1, double e2, double e3, double hi)
{
    double lo = 0.0;
    double g_lo = e0;
    double g_hi = e0 + hi * (e1 + hi * (e2 + hi * e3));
    double tol = 1e-13 * (fabs(e1) + 2.0 * fabs(e2) + 3.0 * fabs(e3));
    int side = 0;
    for (int it = 0; it < ROOT_ITERATIONS; it++) {
        if (hi - lo <= 1e-13)
            break;
        double den = g_hi - g_lo;
        double mid = den != 0.0 ? lo - g_lo * (hi - lo) / den : 0.5 * (lo + hi);
        if (!(lo < mid && mid < hi))
            mid = 0.5 * (lo + hi);
        double g_mid = e0 + mid * (e1 + mid * (e2 + mid * e3));
        if (fabs(g_mid) <= tol)
            return mid;
        if ((g_mid > 0.0) == (g_lo > 0.0)) {
            lo = mid;
            g_lo = g_mid;
            if (side == -1)
                g_hi *= 0.5;
            side = -1;
        } else {
            hi = mid;
            g_hi = g_mid;
            if (side == 1)
                g_lo *= 0.5;
            side = 1;
        }
    }
    return hi;
}

/* events.py _locate: returns s, the region there in *r_out */
static inline double locate(long model, const double *p, double z_offset, double z0, double v0, double z1, double v1,
                            double h, int r0, double s_hi, int *r_out)
{
    double c0 = z0;
    double c1 = h * v0;
    double c2 = -3.0 * z0 - 2.0 * h * v0 + 3.0 * z1 - h * v1;
    double c3 = 2.0 * z0 + h * v0 - 2.0 * z1 + h * v1;
    double zh, vh;
    hermite(z0, v0, z1, v1, h, s_hi, &zh, &vh);
    int changed = r0 ^ region(model, p, z_offset + zh, vh);
    double best = s_hi;
    if (changed & CONTACT)
        best = py_min(best, root_in(c0 + z_offset - p[0], c1, c2, c3, s_hi));
    if (changed & RETRACT)
        best = py_min(best, root_in(c1, 2.0 * c2, 3.0 * c3, 0.0, s_hi));
    if (changed & CLIPPED) {
        double q = p[4] / h;
        best = py_min(best, root_in(p[2] * (p[0] - z_offset - c0) - q * c1, -p[2] * c1 - 2.0 * q * c2,
                                    -p[2] * c2 - 3.0 * q * c3, -p[2] * c3, s_hi));
    }
    double nudge = 1e-14;
    for (int it = 0; it < 24; it++) {
        double zb, vb;
        hermite(z0, v0, z1, v1, h, best, &zb, &vb);
        int r = region(model, p, z_offset + zb, vb);
        if (r != r0 || best >= s_hi) {
            *r_out = r;
            return best;
        }
        best = py_min(s_hi, best + nudge);
        nudge *= 4.0;
    }
    *r_out = region(model, p, z_offset + zh, vh);
    return s_hi;
}

/* events.py _needs_cut, as a count: more than one piece exactly when it says yes */
static inline long pieces_for(const double *p, double gap0, double v0, double a, double gap1, double dt, double beta,
                              double k, double inv_m)
{
    if (beta <= 0.0)
        return 1;
    double travel = fabs(v0) * dt + 0.5 * fabs(a) * dt * dt;
    double gap_p = gap0 + v0 * dt + 0.5 * a * dt * dt;
    double d0 = gap0 - p[0];
    double d1 = gap_p - p[0];
    double scale = ((d0 > 0.0) != (d1 > 0.0)) ? p[0] : py_min(fabs(d0), fabs(d1)) + p[0];
    long pieces = 1;
    if (travel > beta * scale)
        pieces = py_min_long((long)ceil(travel / (beta * scale)), MAX_PIECES);
    double deepest = py_min(py_min(gap0, gap_p), gap1);
    if (deepest < p[0]) {
        double turn = sqrt((k + 1.5 * p[2] * sqrt(p[0] - deepest)) * inv_m) * dt;
        if (turn > STIFF_PHASE * beta)
            pieces = py_max_long(pieces, py_min_long((long)ceil(turn / (STIFF_PHASE * beta)), MAX_PIECES));
    }
    return pieces;
}

/* events.py _piece_length */
static inline double piece_length(const double *p, double gap, double v, double a, double dt, double beta, double k,
                                  double inv_m)
{
    double speed = fabs(v) + 0.5 * fabs(a) * dt;
    if (speed == 0.0)
        return 1.0;
    double h = beta * (fabs(gap - p[0]) + p[0]) / speed;
    if (gap < p[0])
        h = py_min(h, STIFF_PHASE * beta / sqrt((k + 1.5 * p[2] * sqrt(p[0] - gap)) * inv_m));
    return h / dt;
}

/* events.py _near_step_stands (0 = stands): not inlined (a separate function in numba too) */
__attribute__((noinline)) static long near_step_pieces(long model, const double *p, double gap0, double gap1, double v,
                                                       double v1, double a, double dt, double beta, double k,
                                                       double inv_m)
{
    long pieces = pieces_for(p, gap0, v, a, gap1, dt, beta, k, inv_m);
    if (pieces == 1) {
        if (gap0 > p[0] && gap1 > p[0]) {
            if ((v > 0.0) == (v1 > 0.0)
                || (model != MODEL_HYSTERESIS_DMT
                    && py_min(gap0, gap1) - py_max(fabs(v), fabs(v1)) * dt > p[0]))
                return 0;
        } else if (gap0 <= p[0] && gap1 <= p[0] && (v > 0.0) == (v1 > 0.0)
                   && region(model, p, gap1, v1) == region(model, p, gap0, v)) {
            return 0;
        }
    }
    return pieces;
}

/* events.py plain_step_stands (0 = stands) */
static inline long plain_step_pieces(long model, const double *p, double z_offset, double z, double v, double z1,
                                     double v1, double a, double dt, double beta, double k, double inv_m)
{
    if (model == MODEL_NONE)
        return 0;
    double gap0 = z_offset + z;
    double gap1 = z_offset + z1;
    if (beta * (py_min(gap0, gap1) - p[0]) > 1.5 * dt * py_max(fabs(v), fabs(v1))
        && (model != MODEL_HYSTERESIS_DMT || (v > 0.0) == (v1 > 0.0)))
        return 0;
    return near_step_pieces(model, p, gap0, gap1, v, v1, a, dt, beta, k, inv_m);
}

typedef struct {
    double z, v, work, drive, damping, impulse;
    long split, extra;
} full_t;

/* events.py event_step_full: not inlined (numba calls it as a separate function) */
__attribute__((noinline)) static full_t event_step_full(double z, double v, double f1, double fth, double d0,
                                                        double dh, double d1, double k, double c, double inv_m,
                                                        long model, const double *p, double z_offset, double dt,
                                                        long spp, double beta, double z1, double v1, double w,
                                                        double wd, double wc, double wi)
{
    long split = 0;
    long extra = -1;
    double work = 0.0, drive = 0.0, damping = 0.0, impulse = 0.0;
    double za = z;
    double va = v;
    double a = (-k * z - c * v + d0 + f1 + fth) * inv_m;
    double w_step = 2.0 * PI / (double)spp;
    double cos_p, sin_p;
    cos_sin(w_step, &cos_p, &sin_p);
    double ds0 = (d0 * cos_p - d1) / sin_p;
    double u0 = 0.0;
    double d_a = d0;
    double d_e = d1;
    int r = region(model, p, z_offset + z, v);
    step_t st;
    while (u0 < 1.0) {
        double hq = beta > 0.0 ? piece_length(p, z_offset + za, va, a, dt, beta, k, inv_m) : 1.0;
        double rest = 1.0 - u0;
        double u1;
        if (hq >= rest || extra >= MAX_PIECES - 2)
            u1 = 1.0;
        else if (hq > 0.5 * rest)
            u1 = u0 + 0.5 * rest;
        else
            u1 = u0 + hq;
        extra += 1;
        if (!(u0 == 0.0 && u1 == 1.0)) {
            d_e = drive_at(d0, ds0, w_step, u1);
            st = rk4_in(za, va, fth, d_a, drive_at(d0, ds0, w_step, 0.5 * (u0 + u1)), d_e, k, c, inv_m, model, p,
                        z_offset, (u1 - u0) * dt, r);
            z1 = st.z; v1 = st.v; w = st.work; wd = st.drive; wc = st.damping; wi = st.impulse;
        }
        double h_piece = (u1 - u0) * dt;
        double s_hi = other(model, p, z_offset, za, va, z1, v1, h_piece, r);
        if (s_hi > 0.0 && u0 == 0.0 && u1 == 1.0) {
            st = rk4_in(za, va, fth, d0, dh, d1, k, c, inv_m, model, p, z_offset, dt, r);
            z1 = st.z; v1 = st.v; w = st.work; wd = st.drive; wc = st.damping; wi = st.impulse;
            extra += 1;
            s_hi = other(model, p, z_offset, za, va, z1, v1, dt, r);
        }
        double s_start = u0;
        if (s_hi > 0.0) {
            split = 1;
            double d_start = d_a;
            for (int it = 0; it < MAX_SWITCHES; it++) {
                int r_next;
                double s = locate(model, p, z_offset, za, va, z1, v1, (u1 - s_start) * dt, r, s_hi, &r_next);
                double s_switch = s_start + s * (u1 - s_start);
                double d_switch = drive_at(d0, ds0, w_step, s_switch);
                st = rk4_in(za, va, fth, d_start, drive_at(d0, ds0, w_step, 0.5 * (s_start + s_switch)), d_switch, k,
                            c, inv_m, model, p, z_offset, (s_switch - s_start) * dt, r);
                za = st.z; va = st.v;
                work += st.work;
                drive += st.drive;
                damping += st.damping;
                impulse += st.impulse;
                s_start = s_switch;
                r = r_next;
                d_start = d_switch;
                st = rk4_in(za, va, fth, d_start, drive_at(d0, ds0, w_step, 0.5 * (s_start + u1)), d_e, k, c, inv_m,
                            model, p, z_offset, (u1 - s_start) * dt, r);
                z1 = st.z; v1 = st.v; w = st.work; wd = st.drive; wc = st.damping; wi = st.impulse;
                extra += 2;
                double h2 = (u1 - s_start) * dt;
                s_hi = h2 > 0.0 ? other(model, p, z_offset, za, va, z1, v1, h2, r) : -1.0;
                if (s_hi < 0.0)
                    break;
            }
            if (s_hi >= 0.0) /* MAX_SWITCHES reached: go on with the end state's law */
                r = region(model, p, z_offset + z1, v1);
        }
        work += w;
        drive += wd;
        damping += wc;
        impulse += wi;
        /* the acceleration at the piece's end (in the law it ends in) sizes the next piece */
        a = (-k * z1 - c * v1 + d_e + force_in(model, p, z_offset + z1, v1, r) + fth) * inv_m;
        za = z1;
        va = v1;
        u0 = u1;
        d_a = d_e;
    }
    full_t out = {za, va, work, drive, damping, impulse, split, extra};
    return out;
}

/* events.py event_step (inlined) */
static inline full_t event_step(double z, double v, double f1, double fth, double d0, double dh, double d1, double k,
                                double c, double inv_m, long model, const double *p, double z_offset, double h,
                                double hh, double dt, double dth, double sixth, double dt_sixth, long spp, double beta)
{
    step_t st = rk4_step_work(z, v, f1, fth, d0, dh, d1, k, c, inv_m, model, p, z_offset, h, hh, dt, dth, sixth,
                              dt_sixth);
    long pieces = plain_step_pieces(model, p, z_offset, z, v, st.z, st.v,
                                    (-k * z - c * v + d0 + f1 + fth) * inv_m, dt, beta, k, inv_m);
    if (pieces == 0) {
        full_t out = {st.z, st.v, st.work, st.drive, st.damping, st.impulse, 0, 0};
        return out;
    }
    return event_step_full(z, v, f1, fth, d0, dh, d1, k, c, inv_m, model, p, z_offset, dt, spp, beta, st.z, st.v,
                           st.work, st.drive, st.damping, st.impulse);
}

/* events.py advance_event with the thermal force off and no sample recording */
void advance_event(double *y, long n0, long nsteps, double dt, double inv_m, double k, double c, const double *table,
                   long table_len, long model, const double *p, double z_offset, long spp, double beta, double *stats,
                   double *out_w)
{
    double z = y[0], v = y[1];
    const long period2 = table_len - 1;
    long j = (2 * n0) % period2;
    const double h = 0.5 * dt, sixth = dt / 6.0, hh = h * h, dth = dt * h, dt_sixth = dt * sixth;
    const double fth = -0.0; /* the thermal force off (see above) */
    long splits = 0, extra = 0;
    for (long i = 0; i < nsteps; i++) {
        double f1 = tip_sample_force(model, p, z_offset + z, v);
        full_t st = event_step(z, v, f1, fth, table[j], table[j + 1], table[j + 2], k, c, inv_m, model, p, z_offset,
                               h, hh, dt, dth, sixth, dt_sixth, spp, beta);
        z = st.z;
        v = st.v;
        splits += st.split;
        extra += st.extra;
        if (out_w != NULL) {
            out_w[i] = st.work;
            out_w[nsteps + i] = st.drive;
            out_w[2 * nsteps + i] = st.damping;
            out_w[3 * nsteps + i] = st.impulse;
        }
        j += 2;
        if (j >= period2)
            j -= period2;
    }
    y[0] = z;
    y[1] = v;
    stats[0] += (double)splits;
    stats[1] += (double)extra;
}
