//! Printed markers: dark dots on the gel carried by its lateral displacement (u_x, u_y).
//!
//! A dot printed at c on the undeformed gel sits at c + u(c) in the frame (u bilinear on the
//! grid): those centres are the frame's marker labels, the ground truth of shear. To draw them,
//! each pixel p looks up the gel point it shows, X ≈ p − u(p) (the first-order inverse of
//! x = X + u(X)), finds the nearest printed dot and darkens the pixel by its coverage: the
//! fraction of the pixel inside the dot's disc, linear across one pixel of its rim.

use rayon::prelude::*;
use sparsh_scene::MarkerGrid;

use crate::Surface;
use crate::shadow::sample_bilinear;

/// Centres of every dot (mm, camera frame) on the deformed gel, row by row:
/// c + u(c) for each printed centre c.
pub fn marker_centres_mm(markers: &MarkerGrid, surface: &Surface) -> Vec<[f64; 2]> {
    markers
        .centres_mm()
        .into_iter()
        .map(|c| {
            [
                c[0] + sample_bilinear(surface.ux_mm, surface.grid, c[0], c[1]),
                c[1] + sample_bilinear(surface.uy_mm, surface.grid, c[0], c[1]),
            ]
        })
        .collect()
}

/// Fraction (0–1) of pixel `c` covered by a dot: the gel point it shows, X = p − u(p), against
/// the nearest printed centre, with a rim one pixel wide.
pub fn marker_coverage(markers: &MarkerGrid, surface: &Surface, c: usize) -> f64 {
    let grid = surface.grid;
    let x = grid.x_mm(c % grid.nx) - surface.ux_mm[c];
    let y = grid.y_mm(c / grid.nx) - surface.uy_mm[c];
    let nearest = |v: f64, count: usize| {
        let half = (count as f64 - 1.0) / 2.0;
        (v / markers.pitch_mm + half)
            .round()
            .clamp(0.0, count as f64 - 1.0) as usize
    };
    let centre = markers.centre_mm(nearest(x, markers.cols), nearest(y, markers.rows));
    let d = (x - centre[0]).hypot(y - centre[1]);
    ((markers.radius_mm - d) / grid.cell_mm + 0.5).clamp(0.0, 1.0)
}

/// Darkens `pixels` (RGB, 0–255 scale) where the dots are: I·(1 − darkness·coverage).
pub fn draw_markers(pixels: &mut [[f32; 3]], markers: &MarkerGrid, surface: &Surface) {
    pixels.par_iter_mut().enumerate().for_each(|(c, px)| {
        let k = 1.0 - markers.darkness * marker_coverage(markers, surface, c);
        for v in px.iter_mut() {
            *v *= k as f32;
        }
    });
}

/// A position (mm, camera frame) in pixel coordinates (x = column, y = row; pixel (0, 0)'s
/// centre at (0, 0)), as calibration packs mark contacts.
pub fn mm_to_px(grid: sparsh_scene::Grid, p_mm: [f64; 2]) -> [f64; 2] {
    [
        p_mm[0] / grid.cell_mm + grid.nx as f64 / 2.0 - 0.5,
        p_mm[1] / grid.cell_mm + grid.ny as f64 / 2.0 - 0.5,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use sparsh_scene::Grid;

    const GRID: Grid = Grid {
        nx: 120,
        ny: 90,
        cell_mm: 0.05,
    };
    const MARKERS: MarkerGrid = MarkerGrid {
        cols: 7,
        rows: 5,
        pitch_mm: 0.8,
        radius_mm: 0.15,
        darkness: 1.0,
    };

    fn surface<'a>(ux: &'a [f64], uy: &'a [f64], uz: &'a [f64]) -> Surface<'a> {
        Surface {
            grid: GRID,
            ux_mm: ux,
            uy_mm: uy,
            uz_mm: uz,
        }
    }

    /// The dark pixels' centroid of every dot (from the image, not the label formula).
    fn dot_centroids_mm(pixels: &[[f32; 3]]) -> Vec<[f64; 2]> {
        let mut acc = vec![[0.0f64; 3]; MARKERS.cols * MARKERS.rows];
        for (c, px) in pixels.iter().enumerate() {
            let w = 1.0 - px[0] as f64 / 100.0;
            if w <= 0.0 {
                continue;
            }
            let (x, y) = (GRID.x_mm(c % GRID.nx), GRID.y_mm(c / GRID.nx));
            let col = (x / MARKERS.pitch_mm + 3.0).round() as usize;
            let row = (y / MARKERS.pitch_mm + 2.0).round() as usize;
            let a = &mut acc[row * MARKERS.cols + col];
            a[0] += w * x;
            a[1] += w * y;
            a[2] += w;
        }
        acc.iter().map(|a| [a[0] / a[2], a[1] / a[2]]).collect()
    }

    #[test]
    fn no_displacement_gives_the_printed_grid() {
        let zeros = vec![0.0; GRID.len()];
        let s = surface(&zeros, &zeros, &zeros);
        let centres = marker_centres_mm(&MARKERS, &s);
        assert_eq!(centres.len(), 35);
        for (k, c) in centres.iter().enumerate() {
            let (col, row) = ((k % 7) as f64, (k / 7) as f64);
            assert!((c[0] - (col - 3.0) * 0.8).abs() < 1e-12);
            assert!((c[1] - (row - 2.0) * 0.8).abs() < 1e-12);
        }
    }

    /// A uniform lateral displacement moves every label by exactly that displacement, and the
    /// drawn dots with it (their dark centroids move by it to within 0.05 px, the sampling
    /// error of a disc drawn on pixels).
    #[test]
    fn uniform_displacement_moves_every_dot_by_it() {
        let zeros = vec![0.0; GRID.len()];
        let (dx, dy) = (0.137, -0.061);
        let ux = vec![dx; GRID.len()];
        let uy = vec![dy; GRID.len()];
        let rest = surface(&zeros, &zeros, &zeros);
        let moved = surface(&ux, &uy, &zeros);
        let before = marker_centres_mm(&MARKERS, &rest);
        let after = marker_centres_mm(&MARKERS, &moved);
        for (b, a) in before.iter().zip(&after) {
            assert!((a[0] - b[0] - dx).abs() < 1e-12 && (a[1] - b[1] - dy).abs() < 1e-12);
        }
        let mut img_rest = vec![[100.0f32; 3]; GRID.len()];
        let mut img_moved = img_rest.clone();
        draw_markers(&mut img_rest, &MARKERS, &rest);
        draw_markers(&mut img_moved, &MARKERS, &moved);
        for (b, a) in dot_centroids_mm(&img_rest)
            .iter()
            .zip(&dot_centroids_mm(&img_moved))
        {
            assert!(
                (a[0] - b[0] - dx).abs() < 0.05 * GRID.cell_mm,
                "{a:?} {b:?}"
            );
            assert!(
                (a[1] - b[1] - dy).abs() < 0.05 * GRID.cell_mm,
                "{a:?} {b:?}"
            );
        }
    }

    /// Each dot's drawn area matches its disc, πr², to within a pixel's worth.
    #[test]
    fn drawn_dots_have_the_printed_area() {
        let zeros = vec![0.0; GRID.len()];
        let s = surface(&zeros, &zeros, &zeros);
        let total: f64 = (0..GRID.len())
            .map(|c| marker_coverage(&MARKERS, &s, c))
            .sum::<f64>()
            * GRID.cell_area_mm2();
        let expect = 35.0 * std::f64::consts::PI * 0.15 * 0.15;
        assert!((total / expect - 1.0).abs() < 0.02, "{total} vs {expect}");
    }

    #[test]
    fn pixel_coordinates_put_pixel_centres_on_integers() {
        assert_eq!(mm_to_px(GRID, [GRID.x_mm(7), GRID.y_mm(3)]), [7.0, 3.0]);
    }
}
