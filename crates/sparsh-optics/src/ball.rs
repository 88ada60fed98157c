//! The gel surface under a calibration ball: Hertz's displacement field of an elastic
//! half-space pressed by a rigid sphere, inside and outside the contact.

use sparsh_scene::Grid;

/// Depth d (mm) of a ball of radius R whose contact circle has radius a, from the sphere's
/// geometry a² = 2Rd − d², so d = R − √(R² − a²). Errors when a ≥ R.
pub fn depth_from_contact_radius(
    contact_radius_mm: f64,
    ball_radius_mm: f64,
) -> Result<f64, String> {
    let (a, r) = (contact_radius_mm, ball_radius_mm);
    if !(r.is_finite() && r > 0.0) {
        return Err(format!("ball radius must be > 0 mm, got {r}"));
    }
    if !(a.is_finite() && a > 0.0 && a < r) {
        return Err(format!(
            "contact radius {a:.4} mm must be in (0, {r}) mm, the ball radius"
        ));
    }
    Ok(r - (r * r - a * a).sqrt())
}

/// Hertz normal displacement (mm, positive into the gel) at distance r from the centre of a
/// contact of radius a under a rigid sphere of radius R (Johnson, *Contact Mechanics* 1985,
/// eqs. 3.41a and 3.42b, with the approach δ = a²/R):
/// u(r) = δ − r²/(2R) for r ≤ a; u(r) = δ/(πa²)·[(2a² − r²)·asin(a/r) + a·√(r² − a²)] for r > a.
/// The second form decays as (4/3)δa/(πr) far away and meets the first at r = a with u = δ/2.
pub fn hertz_sphere_displacement_mm(r_mm: f64, contact_radius_mm: f64, ball_radius_mm: f64) -> f64 {
    let (r, a) = (r_mm.abs(), contact_radius_mm);
    let delta = a * a / ball_radius_mm;
    if r <= a {
        delta - r * r / (2.0 * ball_radius_mm)
    } else {
        delta / (std::f64::consts::PI * a * a)
            * ((2.0 * a * a - r * r) * (a / r).asin() + a * (r * r - a * a).sqrt())
    }
}

/// The normal displacement field u_z (mm, negative towards the camera, as in
/// [`crate::Surface`]) of the gel pressed by a ball of radius `ball_radius_mm` whose contact
/// circle, centred at `centre_mm` in the grid's frame, has radius `contact_radius_mm`.
/// Errors when the contact radius is not smaller than the ball's.
pub fn ball_press_uz_mm(
    grid: Grid,
    centre_mm: [f64; 2],
    contact_radius_mm: f64,
    ball_radius_mm: f64,
) -> Result<Vec<f64>, String> {
    depth_from_contact_radius(contact_radius_mm, ball_radius_mm)?;
    Ok((0..grid.len())
        .map(|c| {
            let (i, j) = (c % grid.nx, c / grid.nx);
            let r = (grid.x_mm(i) - centre_mm[0]).hypot(grid.y_mm(j) - centre_mm[1]);
            -hertz_sphere_displacement_mm(r, contact_radius_mm, ball_radius_mm)
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depth_inverts_the_sphere_relation() {
        let (r, d) = (2.0f64, 0.37f64);
        let a = (2.0 * r * d - d * d).sqrt();
        assert!((depth_from_contact_radius(a, r).unwrap() - d).abs() < 1e-12);
        assert!(depth_from_contact_radius(2.5, 2.0).is_err());
    }

    #[test]
    fn hertz_field_is_continuous_and_decays_like_a_point_load() {
        let (a, r) = (0.8, 2.0);
        let delta = a * a / r;
        let inside = hertz_sphere_displacement_mm(a, a, r);
        let outside = hertz_sphere_displacement_mm(a * (1.0 + 1e-9), a, r);
        assert!((inside - delta / 2.0).abs() < 1e-12);
        assert!((outside - inside).abs() < 1e-6);
        // Far field: (4/3)·δ·a/(π r) (series of asin and the square root).
        let far = 200.0 * a;
        let expect = 4.0 / 3.0 * delta * a / (std::f64::consts::PI * far);
        assert!((hertz_sphere_displacement_mm(far, a, r) / expect - 1.0).abs() < 1e-4);
        // Slope is continuous at the rim: −a/R on both sides.
        let h = 1e-6;
        let s_in =
            (hertz_sphere_displacement_mm(a, a, r) - hertz_sphere_displacement_mm(a - h, a, r)) / h;
        let s_out = (hertz_sphere_displacement_mm(a + 2.0 * h, a, r)
            - hertz_sphere_displacement_mm(a + h, a, r))
            / h;
        assert!(
            (s_in + a / r).abs() < 1e-4 && (s_out + a / r).abs() < 1e-2,
            "{s_in} {s_out}"
        );
    }
}
