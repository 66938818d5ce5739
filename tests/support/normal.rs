//! The standard normal distribution function for tests that compare renders with closed forms.

/// `Φ(t)`, the standard normal distribution function (erf is not in std; the Abramowitz–Stegun 7.1.26
/// rational form is accurate to 1.5e-7, far below what the tests assert).
pub fn normal_cdf(t: f64) -> f64 {
    let x = t.abs() / std::f64::consts::SQRT_2;
    let k = 1.0 / (1.0 + 0.327_591_1 * x);
    let poly = k
        * (0.254_829_592
            + k * (-0.284_496_736
                + k * (1.421_413_741 + k * (-1.453_152_027 + k * 1.061_405_429))));
    let erf = 1.0 - poly * (-x * x).exp();
    if t >= 0.0 {
        0.5 * (1.0 + erf)
    } else {
        0.5 * (1.0 - erf)
    }
}

/// `φ(t)`, the standard normal density.
#[allow(dead_code)]
pub fn normal_pdf(t: f64) -> f64 {
    (-0.5 * t * t).exp() / (2.0 * std::f64::consts::PI).sqrt()
}
