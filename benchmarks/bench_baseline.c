/* Baseline for `afm_study bench`: the same RK4 + DMT step as afm_ros/core/physics/integrators.py
 * (force at every stage, drive read from a half-step table indexed by the integer step), as a
 * tight C loop without recording. Compiled with gcc -O2 at benchmark time and called via ctypes.
 *
 * y = [z, v]; p = [a0, H R / 6, 4/3 E* sqrt(R), H R / (6 a0^2)]; table has 2 spp + 1 entries.
 */
#include <math.h>

static inline double dmt(const double *p, double gap)
{
    if (gap > p[0])
        return -p[1] / (gap * gap);
    double delta = p[0] - gap;
    return -p[3] + p[2] * delta * sqrt(delta);
}

void rk4_dmt(double *y, long n0, long nsteps, double dt, double inv_m, double k, double c,
             const double *table, long table_len, const double *p, double z_offset)
{
    double z = y[0], v = y[1];
    const long period2 = table_len - 1;
    long j = (2 * n0) % period2;
    const double h = 0.5 * dt, sixth = dt / 6.0, hh = h * h, dth = dt * h, dt_sixth = dt * sixth;
    for (long i = 0; i < nsteps; i++) {
        double f1 = dmt(p, z_offset + z);
        double drive_half = table[j + 1];
        double a1 = (-k * z - c * v + table[j] + f1) * inv_m;
        double z2 = z + h * v, v2 = v + h * a1;
        double a2 = (-k * z2 - c * v2 + drive_half + dmt(p, z_offset + z2)) * inv_m;
        double z3 = z2 + hh * a1, v3 = v + h * a2;
        double a3 = (-k * z3 - c * v3 + drive_half + dmt(p, z_offset + z3)) * inv_m;
        double z_dt = z + dt * v;
        double z4 = z_dt + dth * a2, v4 = v + dt * a3;
        double a4 = (-k * z4 - c * v4 + table[j + 2] + dmt(p, z_offset + z4)) * inv_m;
        z = z_dt + dt_sixth * (a1 + a2 + a3);
        v = (v + sixth * (a1 + 2.0 * (a2 + a3))) + sixth * a4;
        j += 2;
        if (j >= period2)
            j -= period2;
    }
    y[0] = z;
    y[1] = v;
}
