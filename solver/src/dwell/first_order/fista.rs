//! FISTA (Beck & Teboulle 2009) with gradient-based adaptive restart (O'Donoghue & Candes
//! 2015), on the scaled variables of [`super`]; the certificate and step rules are there.

use super::*;

/// FISTA with gradient-based adaptive restart from the feasible point `x`.
pub(super) fn fista(it: Iteration<'_, '_>, mut x: Vec<f64>) -> Outcome {
    let Iteration {
        data,
        work,
        bounds,
        lip,
        limits,
        observer,
    } = it;
    let mut lip = lip;
    let n = x.len();
    let rho = data.rho;
    let mut y = x.clone();
    let mut x_new = vec![0.0; n];
    let mut theta = 1.0_f64;
    let mut best_f = f64::INFINITY;
    let max_it = limits.max_it;
    let mut status = Status::MaxIterations;
    let mut cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
    let mut it = 0;
    let mut reports = Reports::new(0);
    while it < max_it {
        it += 1;
        // Projected gradient step from the extrapolated point y and, in the same pass, the
        // gradient-based restart test (y - x_new)'(x_new - x) > 0 (summed in fixed chunks).
        data.normal_gradient(&y, true, work);
        let step = 1.0 / lip;
        let restart_test = {
            let (g, sc, lo, hi) = (&work.g, &data.s, &data.lo_w, &data.hi_w);
            let (y, x) = (&y, &x);
            fill_and_sum(&mut x_new, &mut work.partials, |j| {
                let v = (y[j] - step * sc[j] * (g[j] + rho)).max(lo[j]).min(hi[j]);
                (v, (y[j] - v) * (v - x[j]))
            })
        };
        if restart_test > 0.0 {
            theta = 1.0;
            y.copy_from_slice(&x_new);
        } else {
            let theta_next = 0.5 * (1.0 + (1.0 + 4.0 * theta * theta).sqrt());
            let beta = (theta - 1.0) / theta_next;
            y.par_iter_mut()
                .zip(x_new.par_iter().zip(x.par_iter()))
                .for_each(|(y, (xn, x))| *y = xn + beta * (xn - x));
            theta = theta_next;
        }
        std::mem::swap(&mut x, &mut x_new);

        if reports.due(it) || it == max_it {
            cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
            reports.report(observer, it, (cert.f, cert.kkt), true);
            if cert.f > best_f * (1.0 + 1e-12) + f64::MIN_POSITIVE {
                // The objective rose: the step was too long. Halve it and restart the momentum.
                lip *= 2.0;
                theta = 1.0;
                y.copy_from_slice(&x);
            }
            best_f = best_f.min(cert.f);
            if let Some(s) = stop_or_cancel(limits, observer, &cert, it) {
                status = s;
                break;
            }
        }
    }
    if status == Status::MaxIterations && it != reports.last {
        cert = certificate(data, &x, work, bounds, &limits.kkt_norm);
    }
    (status, x, it, cert)
}
