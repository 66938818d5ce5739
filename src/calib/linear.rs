//! Closed-form estimators: Hartley-normalised DLT for the 3×4 projection matrix, its RQ decomposition
//! into `K[R|t]`, planar homographies, and Zhang's closed-form intrinsics from homographies.
//!
//! ## Normalised DLT
//! Each correspondence `x ≃ P X` gives two rows of `A p = 0` (`p` = P row-major):
//! `[Xᵀ, 0ᵀ, −u Xᵀ]` and `[0ᵀ, Xᵀ, −v Xᵀ]`. Points are first normalised (Hartley): 2D translated to their
//! centroid and scaled to mean distance √2, 3D to mean distance √3, which makes the SVD well conditioned;
//! the solution is the right singular vector of the smallest singular value, de-normalised as
//! `P = T⁻¹ P̃ U`. nalgebra's SVD is thin when rows < columns, which would drop the null vector: systems
//! are padded with zero rows to be at least square. SVDs are bounded ([`SVD_MAX_ITERATIONS`]).
//!
//! ## RQ
//! `M = K R` with `K` upper triangular (positive diagonal, `K₃₃ = 1` after scaling) and `R` a rotation,
//! computed from a QR decomposition of the row-reversed, transposed `M`. `P` is first given the sign that
//! makes `det M > 0`, so that `det R = +1` and points in front of the camera have positive depth.

use nalgebra::{
    DMatrix, Matrix3, Matrix3x4, Matrix4, Rotation3, SMatrix, SVector, Vector2, Vector3,
};

use super::CalibError;
use crate::camera::Pose;

/// Iteration limit for every SVD in this module.
pub const SVD_MAX_ITERATIONS: usize = 1000;
/// Relative thickness below which a 3D point set is treated as coplanar.
pub const COPLANAR_TOLERANCE: f64 = 1e-6;
/// Ratio of the second-smallest to the largest singular value below which a DLT system is rank-deficient.
pub const RANK_TOLERANCE: f64 = 1e-9;

/// 2D Hartley normalisation: returns `T` with `x̃ = T x`, centroid 0 and mean distance √2.
pub fn normalize_2d(points: &[Vector2<f64>]) -> Result<Matrix3<f64>, CalibError> {
    let n = points.len() as f64;
    let c = points.iter().fold(Vector2::zeros(), |a, p| a + p) / n;
    let mean_d = points.iter().map(|p| (p - c).norm()).sum::<f64>() / n;
    if !(mean_d > 0.0) || !mean_d.is_finite() {
        return Err(CalibError::Degenerate {
            reason: "all image points coincide".into(),
        });
    }
    let s = std::f64::consts::SQRT_2 / mean_d;
    Ok(Matrix3::new(
        s,
        0.0,
        -s * c.x,
        0.0,
        s,
        -s * c.y,
        0.0,
        0.0,
        1.0,
    ))
}

/// 3D Hartley normalisation: returns `U` with `X̃ = U X`, centroid 0 and mean distance √3.
pub fn normalize_3d(points: &[Vector3<f64>]) -> Result<Matrix4<f64>, CalibError> {
    let n = points.len() as f64;
    let c = points.iter().fold(Vector3::zeros(), |a, p| a + p) / n;
    let mean_d = points.iter().map(|p| (p - c).norm()).sum::<f64>() / n;
    if !(mean_d > 0.0) || !mean_d.is_finite() {
        return Err(CalibError::Degenerate {
            reason: "all 3D points coincide".into(),
        });
    }
    let s = 3f64.sqrt() / mean_d;
    let mut u = Matrix4::identity() * s;
    u[(0, 3)] = -s * c.x;
    u[(1, 3)] = -s * c.y;
    u[(2, 3)] = -s * c.z;
    u[(3, 3)] = 1.0;
    Ok(u)
}

/// Centroid and scatter matrix `Σ (p − c)(p − c)ᵀ` of a point set.
fn centroid_scatter(points: &[Vector3<f64>]) -> (Vector3<f64>, Matrix3<f64>) {
    let n = points.len().max(1) as f64;
    let c = points.iter().fold(Vector3::zeros(), |a, p| a + p) / n;
    let s = points.iter().fold(Matrix3::zeros(), |s, p| {
        let d = p - c;
        s + d * d.transpose()
    });
    (c, s)
}

/// Thickness of a 3D point set relative to its extent: √(λ_min/λ_max) of its scatter matrix.
/// Zero for coplanar points.
pub fn relative_thickness(points: &[Vector3<f64>]) -> f64 {
    let (_, s) = centroid_scatter(points);
    let eig = s.symmetric_eigenvalues();
    let max = eig.max();
    let min = eig.min().max(0.0);
    if max <= 0.0 { 0.0 } else { (min / max).sqrt() }
}

/// A rigid frame for a planar point set: `plane_from_rig` maps the points to `z ≈ 0`.
pub fn plane_frame(points: &[Vector3<f64>]) -> Pose {
    let (c, s) = centroid_scatter(points);
    let eig = s.symmetric_eigen();
    // Columns sorted by decreasing eigenvalue: in-plane axes first, normal last.
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    let e0: Vector3<f64> = eig.eigenvectors.column(order[0]).into_owned();
    let e1: Vector3<f64> = eig.eigenvectors.column(order[1]).into_owned();
    let e2 = e0.cross(&e1);
    let r = Matrix3::from_rows(&[e0.transpose(), e1.transpose(), e2.transpose()]);
    let rotation = Rotation3::from_matrix_unchecked(r);
    Pose {
        rotation,
        translation: -(rotation * c),
    }
}

/// Null vector of `A` (right singular vector of the smallest singular value), with the ratio
/// `σ_{second smallest} / σ_max` used to detect rank deficiency.
fn null_vector(a: DMatrix<f64>) -> Result<(nalgebra::DVector<f64>, f64), CalibError> {
    let cols = a.ncols();
    let a = if a.nrows() < cols {
        // nalgebra's SVD is thin: pad to square so V has all `cols` right singular vectors.
        let mut padded = DMatrix::zeros(cols, cols);
        padded.rows_mut(0, a.nrows()).copy_from(&a);
        padded
    } else {
        a
    };
    let svd = nalgebra::SVD::try_new(a, false, true, 1e-15, SVD_MAX_ITERATIONS).ok_or(
        CalibError::SvdNotConverged {
            iterations: SVD_MAX_ITERATIONS,
        },
    )?;
    let v_t = svd.v_t.ok_or(CalibError::SvdNotConverged {
        iterations: SVD_MAX_ITERATIONS,
    })?;
    let mut order: Vec<usize> = (0..svd.singular_values.len()).collect();
    order.sort_by(|&i, &j| svd.singular_values[i].total_cmp(&svd.singular_values[j]));
    let smallest = order[0];
    let second = svd.singular_values[order[1]];
    let largest = svd.singular_values[order[order.len() - 1]];
    let ratio = if largest > 0.0 { second / largest } else { 0.0 };
    Ok((v_t.row(smallest).transpose(), ratio))
}

/// The DLT core shared by the projection matrix and the homography: for normalised homogeneous source
/// points `X̃` (dimension `D`) and image points normalised by `t`, stack the rows
/// `[X̃ᵀ, 0ᵀ, −u X̃ᵀ]`, `[0ᵀ, X̃ᵀ, −v X̃ᵀ]` and return the null vector (row-major `3×D` matrix),
/// refusing a rank-deficient system.
fn homogeneous_dlt<const D: usize>(
    src: &[SVector<f64, D>],
    image: &[Vector2<f64>],
    t: &Matrix3<f64>,
) -> Result<nalgebra::DVector<f64>, CalibError> {
    let mut a = DMatrix::zeros(2 * src.len(), 3 * D);
    for (i, (xh, x2)) in src.iter().zip(image).enumerate() {
        let xn = t * x2.push(1.0);
        let (uu, vv) = (xn.x / xn.z, xn.y / xn.z);
        for k in 0..D {
            a[(2 * i, k)] = xh[k];
            a[(2 * i, 2 * D + k)] = -uu * xh[k];
            a[(2 * i + 1, D + k)] = xh[k];
            a[(2 * i + 1, 2 * D + k)] = -vv * xh[k];
        }
    }
    let (v, ratio) = null_vector(a)?;
    if ratio < RANK_TOLERANCE {
        return Err(CalibError::RankDeficient { ratio });
    }
    Ok(v)
}

fn invert_normalisation(t: &Matrix3<f64>) -> Result<Matrix3<f64>, CalibError> {
    t.try_inverse().ok_or(CalibError::Degenerate {
        reason: "image normalisation not invertible".into(),
    })
}

fn check_finite_3d(points3: &[Vector3<f64>], points2: &[Vector2<f64>]) -> Result<(), CalibError> {
    if let Some(i) = points3
        .iter()
        .position(|p| !p.iter().all(|v| v.is_finite()))
    {
        return Err(CalibError::NonFinite {
            what: "3D point".into(),
            index: i,
        });
    }
    if let Some(i) = points2
        .iter()
        .position(|p| !p.iter().all(|v| v.is_finite()))
    {
        return Err(CalibError::NonFinite {
            what: "image point".into(),
            index: i,
        });
    }
    Ok(())
}

/// Normalised DLT: the 3×4 projection matrix from ≥ 6 non-coplanar 2D–3D correspondences.
/// The result is scaled to unit Frobenius norm with `det(P[:, :3]) > 0`.
pub fn dlt(
    points3: &[Vector3<f64>],
    points2: &[Vector2<f64>],
) -> Result<Matrix3x4<f64>, CalibError> {
    if points3.len() != points2.len() {
        return Err(CalibError::Degenerate {
            reason: format!(
                "{} 3D points but {} image points",
                points3.len(),
                points2.len()
            ),
        });
    }
    if points3.len() < 6 {
        return Err(CalibError::TooFewPoints {
            got: points3.len(),
            need: 6,
        });
    }
    check_finite_3d(points3, points2)?;
    let thickness = relative_thickness(points3);
    if thickness < COPLANAR_TOLERANCE {
        return Err(CalibError::Coplanar { thickness });
    }
    let t = normalize_2d(points2)?;
    let u = normalize_3d(points3)?;
    let src: Vec<SVector<f64, 4>> = points3.iter().map(|x| u * x.push(1.0)).collect();
    let p = homogeneous_dlt(&src, points2, &t)?;
    let pn = Matrix3x4::from_row_slice(p.as_slice());
    let t_inv = invert_normalisation(&t)?;
    let mut pm = t_inv * pn * u;
    let det = pm.fixed_view::<3, 3>(0, 0).determinant();
    if det < 0.0 {
        pm = -pm;
    }
    let norm = pm.norm();
    Ok(pm / norm)
}

/// RQ decomposition `M = K R`: `K` upper triangular with positive diagonal, `R` orthogonal.
/// `det R` has the sign of `det M`.
pub fn rq3(m: &Matrix3<f64>) -> (Matrix3<f64>, Matrix3<f64>) {
    // Reversal permutation E (E = Eᵀ = E⁻¹). (E M)ᵀ = Q U  ⇒  M = (E Uᵀ E)(E Qᵀ).
    let e = Matrix3::new(0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 0.0);
    let qr = (e * m).transpose().qr();
    let q = qr.q();
    let upper = qr.r();
    let mut k = e * upper.transpose() * e;
    let mut r = e * q.transpose();
    for i in 0..3 {
        if k[(i, i)] < 0.0 {
            // K D, D R with D = diag(±1): flips column i of K and row i of R.
            for row in 0..3 {
                k[(row, i)] = -k[(row, i)];
            }
            for col in 0..3 {
                r[(i, col)] = -r[(i, col)];
            }
        }
    }
    (k, r)
}

/// Decompose a projection matrix into `K` (with `K₃₃ = 1`) and `cam_from_rig`.
pub fn decompose_projection(p: &Matrix3x4<f64>) -> Result<(Matrix3<f64>, Pose), CalibError> {
    let mut p = *p;
    if p.fixed_view::<3, 3>(0, 0).determinant() < 0.0 {
        p = -p;
    }
    let m: Matrix3<f64> = p.fixed_view::<3, 3>(0, 0).into_owned();
    if m.determinant().abs() < 1e-300 || !m.iter().all(|v| v.is_finite()) {
        return Err(CalibError::Degenerate {
            reason: "projection matrix has a singular left 3×3 block".into(),
        });
    }
    let (k_scaled, r) = rq3(&m);
    let scale = k_scaled[(2, 2)];
    let k = k_scaled / scale;
    let k_inv = k_scaled.try_inverse().ok_or(CalibError::Degenerate {
        reason: "camera matrix not invertible".into(),
    })?;
    let t: Vector3<f64> = k_inv * p.column(3);
    Ok((
        k,
        Pose {
            rotation: Rotation3::from_matrix_unchecked(r),
            translation: t,
        },
    ))
}

/// Normalised DLT homography `x ≃ H X` from ≥ 4 plane points (`X` in plane coordinates).
pub fn homography(
    plane: &[Vector2<f64>],
    image: &[Vector2<f64>],
) -> Result<Matrix3<f64>, CalibError> {
    if plane.len() != image.len() {
        return Err(CalibError::Degenerate {
            reason: "plane and image point counts differ".into(),
        });
    }
    if plane.len() < 4 {
        return Err(CalibError::TooFewPoints {
            got: plane.len(),
            need: 4,
        });
    }
    let tp = normalize_2d(plane)?;
    let ti = normalize_2d(image)?;
    let src: Vec<SVector<f64, 3>> = plane.iter().map(|x| tp * x.push(1.0)).collect();
    let h = homogeneous_dlt(&src, image, &ti)?;
    let hn = Matrix3::from_row_slice(h.as_slice());
    let ti_inv = invert_normalisation(&ti)?;
    let hm = ti_inv * hn * tp;
    let s = hm[(2, 2)];
    Ok(if s.abs() > 1e-12 {
        hm / s
    } else {
        hm / hm.norm()
    })
}

/// The homography `x ≃ H X` normalised by `H₃₃ = 1`, fitted by least squares to the pairs `(X, x)`
/// through its eight normal equations: a fraction of the cost of [`homography`]'s SVD, for callers
/// that fit many small ones. Only valid where `X = 0` is not mapped to infinity; the caller centres
/// and scales its points (`None` for fewer than four pairs or singular normal equations).
pub fn homography_h33(
    pairs: impl IntoIterator<Item = (Vector2<f64>, Vector2<f64>)>,
) -> Option<Matrix3<f64>> {
    // With h = (h₁₁ h₁₂ h₁₃ h₂₁ h₂₂ h₂₃ h₃₁ h₃₂), each pair (x, y) → (u, v) gives
    // u = h₁₁x + h₁₂y + h₁₃ − h₃₁xu − h₃₂yu and the same for v.
    let mut ata = SMatrix::<f64, 8, 8>::zeros();
    let mut atb = SVector::<f64, 8>::zeros();
    let mut n = 0;
    for (q, uv) in pairs {
        let (x, y) = (q.x, q.y);
        let rows = [
            (
                SVector::<f64, 8>::from([x, y, 1.0, 0.0, 0.0, 0.0, -x * uv.x, -y * uv.x]),
                uv.x,
            ),
            (
                SVector::<f64, 8>::from([0.0, 0.0, 0.0, x, y, 1.0, -x * uv.y, -y * uv.y]),
                uv.y,
            ),
        ];
        for (row, rhs) in rows {
            ata.ger(1.0, &row, &row, 1.0);
            atb.axpy(rhs, &row, 1.0);
        }
        n += 1;
    }
    if n < 4 {
        return None;
    }
    let h = ata.cholesky()?.solve(&atb);
    Some(Matrix3::new(
        h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0,
    ))
}

/// Zhang's closed-form intrinsics from ≥ 2 homographies (skew constrained to zero), computed in
/// coordinates normalised by the image size for conditioning.
pub fn zhang_intrinsics(
    hs: &[Matrix3<f64>],
    image_size: [u32; 2],
) -> Result<Matrix3<f64>, CalibError> {
    if hs.len() < 2 {
        return Err(CalibError::TooFewViews {
            got: hs.len(),
            need: 2,
        });
    }
    let s = 2.0 / f64::from(image_size[0].max(image_size[1]).max(1));
    let cx0 = 0.5 * (f64::from(image_size[0]) - 1.0);
    let cy0 = 0.5 * (f64::from(image_size[1]) - 1.0);
    let nrm = Matrix3::new(s, 0.0, -s * cx0, 0.0, s, -s * cy0, 0.0, 0.0, 1.0);
    let v = |h: &Matrix3<f64>, i: usize, j: usize| -> [f64; 6] {
        let hi = h.column(i);
        let hj = h.column(j);
        [
            hi[0] * hj[0],
            hi[0] * hj[1] + hi[1] * hj[0],
            hi[1] * hj[1],
            hi[2] * hj[0] + hi[0] * hj[2],
            hi[2] * hj[1] + hi[1] * hj[2],
            hi[2] * hj[2],
        ]
    };
    let mut a = DMatrix::zeros(2 * hs.len() + 1, 6);
    for (n, h) in hs.iter().enumerate() {
        let hn = nrm * h;
        let hn = hn / hn.norm();
        let v12 = v(&hn, 0, 1);
        let v11 = v(&hn, 0, 0);
        let v22 = v(&hn, 1, 1);
        for k in 0..6 {
            a[(2 * n, k)] = v12[k];
            a[(2 * n + 1, k)] = v11[k] - v22[k];
        }
    }
    a[(2 * hs.len(), 1)] = 1.0; // B12 = 0 (zero skew)
    let (b, _) = null_vector(a)?;
    let (b11, b12, b22, b13, b23, b33) = (b[0], b[1], b[2], b[3], b[4], b[5]);
    let den = b11 * b22 - b12 * b12;
    let bad = || CalibError::Degenerate {
        reason: "Zhang's closed form found no valid camera: views too similar in orientation"
            .into(),
    };
    if den.abs() < 1e-300 || b11.abs() < 1e-300 {
        return Err(bad());
    }
    let v0 = (b12 * b13 - b11 * b23) / den;
    let lambda = b33 - (b13 * b13 + v0 * (b12 * b13 - b11 * b23)) / b11;
    let alpha2 = lambda / b11;
    let beta2 = lambda * b11 / den;
    if !(alpha2 > 0.0 && beta2 > 0.0) {
        return Err(bad());
    }
    let alpha = alpha2.sqrt();
    let beta = beta2.sqrt();
    let u0 = -b13 * alpha2 / lambda;
    let kn = Matrix3::new(alpha, 0.0, u0, 0.0, beta, v0, 0.0, 0.0, 1.0);
    let nrm_inv = nrm.try_inverse().ok_or_else(bad)?;
    let k = nrm_inv * kn;
    if !k.iter().all(|x| x.is_finite()) {
        return Err(bad());
    }
    Ok(k / k[(2, 2)])
}

/// Focal length from one homography with the principal point assumed known and square pixels.
pub fn focal_from_homography(h: &Matrix3<f64>, cx: f64, cy: f64) -> Option<f64> {
    let t = Matrix3::new(1.0, 0.0, -cx, 0.0, 1.0, -cy, 0.0, 0.0, 1.0);
    let h = t * h;
    let h = h / h.norm();
    // Constraints with B = diag(w, w, 1), w = 1/f²: a·w + c = 0.
    let a1 = h[(0, 0)] * h[(0, 1)] + h[(1, 0)] * h[(1, 1)];
    let c1 = h[(2, 0)] * h[(2, 1)];
    let a2 = h[(0, 0)].powi(2) + h[(1, 0)].powi(2) - h[(0, 1)].powi(2) - h[(1, 1)].powi(2);
    let c2 = h[(2, 0)].powi(2) - h[(2, 1)].powi(2);
    let den = a1 * a1 + a2 * a2;
    if den <= 0.0 {
        return None;
    }
    let w = -(a1 * c1 + a2 * c2) / den;
    (w > 0.0 && w.is_finite()).then(|| 1.0 / w.sqrt())
}

/// Nearest rotation (Frobenius) to a 3×3 matrix.
pub fn nearest_rotation(m: &Matrix3<f64>) -> Result<Rotation3<f64>, CalibError> {
    let svd = nalgebra::SVD::try_new(*m, true, true, 1e-15, SVD_MAX_ITERATIONS).ok_or(
        CalibError::SvdNotConverged {
            iterations: SVD_MAX_ITERATIONS,
        },
    )?;
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(CalibError::SvdNotConverged {
            iterations: SVD_MAX_ITERATIONS,
        });
    };
    let mut r = u * v_t;
    if r.determinant() < 0.0 {
        let mut u2 = u;
        for row in 0..3 {
            u2[(row, 2)] = -u2[(row, 2)];
        }
        r = u2 * v_t;
    }
    Ok(Rotation3::from_matrix_unchecked(r))
}

/// `cam_from_plane` from a homography (plane coordinates `z = 0`) and `K`.
pub fn pose_from_homography(h: &Matrix3<f64>, k: &Matrix3<f64>) -> Result<Pose, CalibError> {
    let k_inv = k.try_inverse().ok_or(CalibError::Degenerate {
        reason: "camera matrix not invertible".into(),
    })?;
    let a = k_inv * h;
    let a1: Vector3<f64> = a.column(0).into_owned();
    let a2: Vector3<f64> = a.column(1).into_owned();
    let a3: Vector3<f64> = a.column(2).into_owned();
    let mut lambda = 2.0 / (a1.norm() + a2.norm());
    if a3.z * lambda < 0.0 {
        lambda = -lambda; // the plane origin must be in front of the camera
    }
    let r1 = a1 * lambda;
    let r2 = a2 * lambda;
    let r3 = r1.cross(&r2);
    let rot = nearest_rotation(&Matrix3::from_columns(&[r1, r2, r3]))?;
    Ok(Pose {
        rotation: rot,
        translation: a3 * lambda,
    })
}

/// `cam_from_rig` from a projection matrix and a known `K`.
pub fn pose_from_projection(p: &Matrix3x4<f64>, k: &Matrix3<f64>) -> Result<Pose, CalibError> {
    let k_inv = k.try_inverse().ok_or(CalibError::Degenerate {
        reason: "camera matrix not invertible".into(),
    })?;
    let a = k_inv * p;
    let m: Matrix3<f64> = a.fixed_view::<3, 3>(0, 0).into_owned();
    let det = m.determinant();
    if !(det.abs() > 0.0) {
        return Err(CalibError::Degenerate {
            reason: "projection matrix has a singular left 3×3 block".into(),
        });
    }
    let s = det.cbrt();
    let rot = nearest_rotation(&(m / s))?;
    Ok(Pose {
        rotation: rot,
        translation: a.column(3) / s,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn rig_points() -> Vec<Vector3<f64>> {
        let mut pts = Vec::new();
        for i in 0..4 {
            for j in 0..3 {
                let (a, b) = (20.0 + 30.0 * i as f64, 20.0 + 30.0 * j as f64);
                pts.push(Vector3::new(a, b, 0.0));
                pts.push(Vector3::new(0.0, a, b));
                pts.push(Vector3::new(b, 0.0, a));
            }
        }
        pts
    }

    fn project_p(p: &Matrix3x4<f64>, x: &Vector3<f64>) -> Vector2<f64> {
        let h = p * x.push(1.0);
        Vector2::new(h.x / h.z, h.y / h.z)
    }

    proptest! {
        #[test]
        fn rq_rebuilds_and_is_proper(vals in proptest::collection::vec(-10.0f64..10.0, 9)) {
            let m = Matrix3::from_row_slice(&vals);
            prop_assume!(m.determinant().abs() > 1e-3);
            let (k, r) = rq3(&m);
            prop_assert!((k * r - m).norm() < 1e-9 * (1.0 + m.norm()));
            prop_assert!((r.transpose() * r - Matrix3::identity()).norm() < 1e-10);
            prop_assert!((r.determinant() - m.determinant().signum()).abs() < 1e-10);
            prop_assert!(k[(1, 0)].abs() < 1e-12 && k[(2, 0)].abs() < 1e-12 && k[(2, 1)].abs() < 1e-12);
            for i in 0..3 { prop_assert!(k[(i, i)] > 0.0); }
        }

        #[test]
        fn dlt_and_decomposition_recover_the_camera(
            fx in 300.0f64..3000.0, aspect in 0.8f64..1.25, cx in 200.0f64..900.0, cy in 150.0f64..700.0,
            skew in -2.0f64..2.0, rv in proptest::collection::vec(-0.6f64..0.6, 3),
            dist in 400.0f64..1500.0,
        ) {
            let k = Matrix3::new(fx, skew, cx, 0.0, fx * aspect, cy, 0.0, 0.0, 1.0);
            // Look at the rig's corner region from a generic direction.
            let r = Rotation3::new(Vector3::new(rv[0], rv[1], rv[2])) * Rotation3::face_towards(&Vector3::new(-1.0, -1.0, -1.0), &Vector3::new(0.0, 0.0, 1.0)).inverse();
            let centre = Vector3::new(dist, dist, dist) / 3f64.sqrt();
            let t = -(r * centre);
            let pose = Pose { rotation: r, translation: t };
            let pts3 = rig_points();
            let mut pm = Matrix3x4::zeros();
            pm.fixed_view_mut::<3, 3>(0, 0).copy_from(&(k * r.matrix()));
            pm.set_column(3, &(k * t));
            prop_assume!(pts3.iter().all(|x| pose.transform(x).z > 10.0));
            let pts2: Vec<_> = pts3.iter().map(|x| project_p(&pm, x)).collect();
            let p_est = dlt(&pts3, &pts2).unwrap();
            // P rebuilt up to scale.
            let scale = pm.norm() / p_est.norm();
            prop_assert!((p_est * scale - pm).norm() < 1e-6 * pm.norm(), "P differs");
            let (k_est, pose_est) = decompose_projection(&p_est).unwrap();
            prop_assert!((k_est - k).norm() < 1e-6 * k.norm());
            let re = pose_est.rotation.matrix();
            prop_assert!((re.transpose() * re - Matrix3::identity()).norm() < 1e-10);
            prop_assert!((re.determinant() - 1.0).abs() < 1e-10);
            prop_assert!((pose_est.centre() - centre).norm() < 1e-6 * centre.norm());
        }
    }

    #[test]
    fn dlt_rejects_coplanar_and_too_few() {
        let pts3: Vec<_> = (0..10)
            .map(|i| Vector3::new(i as f64, (i * i) as f64 % 7.0, 0.0))
            .collect();
        let pts2: Vec<_> = (0..10)
            .map(|i| Vector2::new(i as f64, 2.0 * i as f64))
            .collect();
        assert!(matches!(
            dlt(&pts3, &pts2),
            Err(CalibError::Coplanar { .. })
        ));
        assert!(matches!(
            dlt(&pts3[..5], &pts2[..5]),
            Err(CalibError::TooFewPoints { got: 5, need: 6 })
        ));
        let mut bad = rig_points();
        bad[3].x = f64::NAN;
        let img: Vec<_> = bad.iter().map(|p| Vector2::new(p.x, p.y)).collect();
        assert!(matches!(
            dlt(&bad, &img),
            Err(CalibError::NonFinite { index: 3, .. })
        ));
    }

    #[test]
    fn zhang_recovers_k_from_three_planar_views() {
        let k = Matrix3::new(800.0, 0.0, 330.0, 0.0, 790.0, 250.0, 0.0, 0.0, 1.0);
        let plane: Vec<_> = (0..48)
            .map(|i| Vector2::new((i % 8) as f64 * 25.0, (i / 8) as f64 * 25.0))
            .collect();
        let mut hs = Vec::new();
        for (rx, ry) in [(0.4, 0.1), (-0.2, 0.5), (0.3, -0.4)] {
            let r = Rotation3::from_euler_angles(rx, ry, 0.1);
            let t = Vector3::new(-80.0, -60.0, 600.0);
            let mut h = Matrix3::zeros();
            h.set_column(0, &(k * r.matrix().column(0)));
            h.set_column(1, &(k * r.matrix().column(1)));
            h.set_column(2, &(k * t));
            let img: Vec<_> = plane
                .iter()
                .map(|p| {
                    let x = h * p.push(1.0);
                    Vector2::new(x.x / x.z, x.y / x.z)
                })
                .collect();
            let h_est = homography(&plane, &img).unwrap();
            let pose = pose_from_homography(&h_est, &k).unwrap();
            assert!((pose.translation - t).norm() < 1e-6);
            assert!((pose.rotation.matrix() - r.matrix()).norm() < 1e-9);
            hs.push(h_est);
        }
        let k_est = zhang_intrinsics(&hs, [640, 480]).unwrap();
        assert!((k_est - k).norm() < 1e-6, "{k_est}");
        // Square pixels: the one-view focal estimate is exact.
        let ks = Matrix3::new(800.0, 0.0, 330.0, 0.0, 800.0, 250.0, 0.0, 0.0, 1.0);
        let r = Rotation3::from_euler_angles(0.4, 0.1, 0.1);
        let mut h = Matrix3::zeros();
        h.set_column(0, &(ks * r.matrix().column(0)));
        h.set_column(1, &(ks * r.matrix().column(1)));
        h.set_column(2, &(ks * Vector3::new(-80.0, -60.0, 600.0)));
        let f = focal_from_homography(&h, 330.0, 250.0).unwrap();
        assert!((f - 800.0).abs() < 1e-6, "{f}");
    }
}
