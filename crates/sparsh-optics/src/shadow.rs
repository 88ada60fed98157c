//! Cast shadows: the fraction of each LED that a point of the gel surface sees, found by
//! marching the height field a fixed number of steps toward the light.
//!
//! Heights are h = −u_z (mm toward the camera, the side the LEDs light the gel from); a light at
//! camera-frame z_L < 0 sits at height −z_L. From surface point P the ray toward light L rises
//! with slope r = (h_L − h_P)/D over the horizontal distance D. Marching t = k·Δt (k = 1…steps)
//! along the horizontal direction to L, the highest occluder seen from P has slope
//! m = max_k (h(P + t_k) − h_P)/t_k, and the light's centre clears the surface by the angle
//! θ = atan r − atan m. The LED is a disc of radius ρ seen at distance |L − P|, so of angular
//! radius α = atan(ρ/|L − P|); its visible fraction is taken linear across the penumbra,
//! v = clamp(½ + θ/(2α), 0, 1) (v = 1 if θ ≥ 0 else 0 for a point light). A tilted plane of slope
//! s toward the light is thus in shadow iff s exceeds the light's elevation slope r.
//!
//! The march ends where the ray has cleared the highest point of the field by the penumbra
//! (t ≥ (h_max − h_P)/m_c with m_c = tan(atan r − α): no occluder beyond dims the light), at the
//! light's foot, or at `max_march_mm`, whichever comes first, and always takes `steps` equal
//! steps: per pixel, bounded, no recursion, so a compute shader runs the same arithmetic.
//!
//! Two exact shortcuts skip rays that tile bounds prove fully lit (v = 1): the surface along the
//! ray never rises faster than m_c (tile maxima of the slopes), or never above the cone
//! h_P + t·m_c (tile maxima of the heights). They change the time, not the result. The GPU
//! shader takes the same shortcuts on the same tile bounds, with margins for its f32 arithmetic.

use rayon::prelude::*;
use sparsh_scene::{Grid, Light};

/// How shadows are marched.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShadowSettings {
    /// Samples of the height field along each ray.
    pub steps: u32,
    /// Longest march toward a light (mm).
    pub max_march_mm: f64,
    /// Radius of each LED's emitting disc (mm); 0 gives hard shadows.
    pub led_radius_mm: f64,
}

impl Default for ShadowSettings {
    fn default() -> Self {
        ShadowSettings {
            steps: 32,
            max_march_mm: 6.0,
            led_radius_mm: 1.0,
        }
    }
}

/// A field on the grid (one value per cell, e.g. the surface height in mm) at (x, y) mm in the
/// grid's frame, bilinear between cell centres and held constant beyond the outer centres.
pub fn sample_bilinear(field: &[f64], grid: Grid, x_mm: f64, y_mm: f64) -> f64 {
    let fx = (x_mm / grid.cell_mm + grid.nx as f64 / 2.0 - 0.5).clamp(0.0, (grid.nx - 1) as f64);
    let fy = (y_mm / grid.cell_mm + grid.ny as f64 / 2.0 - 0.5).clamp(0.0, (grid.ny - 1) as f64);
    let (i0, j0) = (fx.floor() as usize, fy.floor() as usize);
    let (i1, j1) = ((i0 + 1).min(grid.nx - 1), (j0 + 1).min(grid.ny - 1));
    let (tx, ty) = (fx - i0 as f64, fy - j0 as f64);
    let at = |i: usize, j: usize| field[j * grid.nx + i];
    let top = at(i0, j0) * (1.0 - tx) + at(i1, j0) * tx;
    let bottom = at(i0, j1) * (1.0 - tx) + at(i1, j1) * tx;
    top * (1.0 - ty) + bottom * ty
}

/// Smallest [`tile_shift`]: tiles are at least 4 cells on a side.
pub(crate) const MIN_TILE_SHIFT: u32 = 2;

/// Side of the tiles whose bounds let [`light_visibility`] skip rays that clear everything:
/// the power of two of cells nearest 0.5 mm, at least 4 (on a ball press under the GelSight
/// LEDs, 0.5 mm tiles balanced marched samples against probes at 0.059 and 0.0295 mm cells).
fn tile_shift(cell_mm: f64) -> u32 {
    (0.5 / cell_mm)
        .log2()
        .round()
        .clamp(MIN_TILE_SHIFT as f64, 10.0) as u32
}

/// The surface height h = −u_z (mm toward the camera) on a grid, with its maximum and, over
/// each tile's 3 × 3 block of tiles, the maximum height and steepest slopes (the shortcuts of
/// [`light_visibility`]).
#[derive(Debug, Clone)]
pub struct HeightField {
    /// Heights, row-major (mm).
    pub height_mm: Vec<f64>,
    /// The grid.
    pub grid: Grid,
    /// Highest point (mm).
    pub max_mm: f64,
    /// Tiles along x and y.
    tiles: [usize; 2],
    /// Tiles are 2^`tile_shift` cells on a side.
    pub(crate) tile_shift: u32,
    /// Highest point within each tile and its eight neighbours (mm).
    pub(crate) block_max_mm: Vec<f64>,
    /// Steepest slopes |∂h/∂x|, |∂h/∂y| of the bilinear surface over the cells whose lower
    /// corner lies within each tile and its eight neighbours: max |h(i+1, j) − h(i, j)| / cell
    /// and max |h(i, j+1) − h(i, j)| / cell.
    pub(crate) block_slope: Vec<[f64; 2]>,
}

impl HeightField {
    /// The height field of the surface u_z (mm, negative toward the camera).
    pub fn from_uz(uz_mm: &[f64], grid: Grid) -> HeightField {
        let height_mm: Vec<f64> = uz_mm.iter().map(|u| -u).collect();
        let max_mm = height_mm.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let tile_shift = tile_shift(grid.cell_mm);
        let tile = 1 << tile_shift;
        let tiles = [grid.nx.div_ceil(tile), grid.ny.div_ceil(tile)];
        let mut tile_max = vec![f64::NEG_INFINITY; tiles[0] * tiles[1]];
        let mut tile_slope = vec![[0.0f64; 2]; tiles[0] * tiles[1]];
        for (c, &h) in height_mm.iter().enumerate() {
            let (i, j) = (c % grid.nx, c / grid.nx);
            let t = (j >> tile_shift) * tiles[0] + (i >> tile_shift);
            tile_max[t] = tile_max[t].max(h);
            let s = &mut tile_slope[t];
            if i + 1 < grid.nx {
                s[0] = s[0].max((height_mm[c + 1] - h).abs() / grid.cell_mm);
            }
            if j + 1 < grid.ny {
                s[1] = s[1].max((height_mm[c + grid.nx] - h).abs() / grid.cell_mm);
            }
        }
        let block = |t: usize, f: &mut dyn FnMut(usize)| {
            let (tx, ty) = (t % tiles[0], t / tiles[0]);
            for y in ty.saturating_sub(1)..(ty + 2).min(tiles[1]) {
                for x in tx.saturating_sub(1)..(tx + 2).min(tiles[0]) {
                    f(y * tiles[0] + x);
                }
            }
        };
        let (mut block_max_mm, mut block_slope) = (Vec::new(), Vec::new());
        for t in 0..tiles[0] * tiles[1] {
            let (mut m, mut s) = (f64::NEG_INFINITY, [0.0f64; 2]);
            block(t, &mut |n| {
                m = m.max(tile_max[n]);
                s = [s[0].max(tile_slope[n][0]), s[1].max(tile_slope[n][1])];
            });
            block_max_mm.push(m);
            block_slope.push(s);
        }
        HeightField {
            height_mm,
            grid,
            max_mm,
            tiles,
            tile_shift,
            block_max_mm,
            block_slope,
        }
    }
}

/// Visible fraction (0–1) of a light at `light` = (x, y, height) mm from the surface point
/// `p` = (x, y, height) mm over the height field (see the module doc for the formula). `p` must
/// be a cell centre with the field's height there (the slope bound measures rises from it).
///
/// Exact shortcuts first: occluder slopes up to m_c = tan(atan r − α) leave the whole LED in
/// view (v = 1). Points of the ray up to t lie within half a tile of probes at t_j = (j + ½)·Δ
/// (Δ the tile's width, j up to t's probe), and their bilinear cells within those probes' 3 × 3
/// blocks of tiles. The samples of probe j's interval are below the cone h_P + t·m_c, and are
/// skipped, when (1) the blocks' steepest slopes up to probe j bound the rise rate along the
/// ray's direction u, |u_x|·s_x + |u_y|·s_y ≤ m_c (then h(P + t·u) − h_P = ∫ u·∇h ≤ t·m_c), or
/// (2) the block's maximum lies below h_P + max(Δt, t_j − Δ/2)·m_c; when every interval passes,
/// so does the whole march. The result is the same with or without the shortcuts; only the
/// time differs.
pub fn light_visibility(
    field: &HeightField,
    p: [f64; 3],
    light: [f64; 3],
    settings: ShadowSettings,
) -> f64 {
    visibility(field, p, light, settings, true)
}

fn visibility(
    field: &HeightField,
    p: [f64; 3],
    light: [f64; 3],
    settings: ShadowSettings,
    shortcut: bool,
) -> f64 {
    let (dx, dy) = (light[0] - p[0], light[1] - p[1]);
    let reach = (dx * dx + dy * dy).sqrt();
    let rise = light[2] - p[2];
    if reach < 1e-9 || rise <= 0.0 {
        return 1.0;
    }
    let slope = rise / reach;
    // tan α of the LED's angular radius; the LED clears slopes up to
    // m_c = tan(atan r − α) = (r − tan α)/(1 + r·tan α) when r > tan α.
    let tan_half_angle = settings.led_radius_mm / (reach * reach + rise * rise).sqrt();
    let clear_slope =
        (slope > tan_half_angle).then(|| (slope - tan_half_angle) / (1.0 + slope * tan_half_angle));
    let march = match clear_slope {
        Some(m) => reach
            .min(settings.max_march_mm)
            .min((field.max_mm - p[2]) / m),
        None => reach.min(settings.max_march_mm),
    };
    if march <= 0.0 {
        return 1.0;
    }
    let dt = march / settings.steps as f64;
    let (ux, uy) = (dx / reach, dy / reach);
    // Samples outside [lo, hi] lie in probe intervals proven clear (slope ≤ m_c): skipping
    // them leaves the maximum, and v, unchanged.
    let (mut lo, mut hi) = (dt, march);
    if let Some(m) = clear_slope.filter(|_| shortcut) {
        let g = field.grid;
        let tile = (1usize << field.tile_shift) as f64;
        let tile_mm = tile * g.cell_mm;
        let probes = (march / tile_mm).ceil() as usize;
        // Probe j at t_j = (j + ½)·Δ, in fractional cell coordinates (as in sample_bilinear).
        let (cx, cy) = (
            p[0] / g.cell_mm + g.nx as f64 / 2.0 - 0.5,
            p[1] / g.cell_mm + g.ny as f64 / 2.0 - 0.5,
        );
        let (step_x, step_y) = (tile * ux, tile * uy);
        let (max_x, max_y) = ((g.nx - 1) as f64, (g.ny - 1) as f64);
        let slope_along = |b: usize| {
            let [sx, sy] = field.block_slope[b];
            ux.abs() * sx + uy.abs() * sy
        };
        // Rise rate along u bounded over the ray up to probe j (a hair of margin keeps the
        // rounding of the march's own quotients on the lit side).
        let (mut rise_rate, lit_rate) = (0.0f64, m * (1.0 - 1e-9));
        (lo, hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for j in 0..probes {
            let s = j as f64 + 0.5;
            let fx = (cx + s * step_x).clamp(0.0, max_x) as usize;
            let fy = (cy + s * step_y).clamp(0.0, max_y) as usize;
            let b = (fy >> field.tile_shift) * field.tiles[0] + (fx >> field.tile_shift);
            rise_rate = rise_rate.max(slope_along(b));
            let t = s * tile_mm;
            let cone = p[2] + dt.max(t - tile_mm / 2.0) * lit_rate;
            if rise_rate > lit_rate && field.block_max_mm[b] > cone {
                lo = lo.min(t - tile_mm / 2.0);
                hi = hi.max(t + tile_mm / 2.0);
            }
        }
        if lo > hi {
            return 1.0;
        }
    }
    let first = ((lo / dt).ceil() as u32).max(1);
    // the march's own end is sample `steps` (march / dt may round below it)
    let last = if hi >= march {
        settings.steps
    } else {
        ((hi / dt).floor() as u32).min(settings.steps)
    };
    let mut occluder = f64::NEG_INFINITY;
    for k in first..=last {
        let t = k as f64 * dt;
        let h = sample_bilinear(&field.height_mm, field.grid, p[0] + t * ux, p[1] + t * uy);
        occluder = occluder.max((h - p[2]) / t);
    }
    let clearance = slope.atan() - occluder.atan();
    penumbra(clearance, tan_half_angle.atan())
}

/// Visible fraction of a disc light of angular radius `half_angle` whose centre clears the
/// horizon by `clearance` (rad): linear across the penumbra, a step for a point light.
pub fn penumbra(clearance: f64, half_angle: f64) -> f64 {
    if half_angle > 0.0 {
        (0.5 + 0.5 * clearance / half_angle).clamp(0.0, 1.0)
    } else if clearance >= 0.0 {
        1.0
    } else {
        0.0
    }
}

/// A light's position as (x, y, height) mm: height = −z (the camera frame's z points into the
/// gel).
pub fn light_point(light: &Light) -> [f64; 3] {
    [
        light.position_mm[0],
        light.position_mm[1],
        -light.position_mm[2],
    ]
}

/// Visible fraction of every light from every cell of the grid, for the surface u_z (mm,
/// negative toward the camera): `lights.len()` values per cell, cells row-major.
pub fn visibilities(
    uz_mm: &[f64],
    grid: Grid,
    lights: &[Light],
    settings: ShadowSettings,
) -> Vec<f64> {
    let field = HeightField::from_uz(uz_mm, grid);
    let points: Vec<[f64; 3]> = lights.iter().map(light_point).collect();
    let mut out = vec![0.0; grid.len() * lights.len()];
    out.par_chunks_mut(lights.len().max(1))
        .enumerate()
        .for_each(|(c, v)| {
            let p = [
                grid.x_mm(c % grid.nx),
                grid.y_mm(c / grid.nx),
                field.height_mm[c],
            ];
            for (v, &l) in v.iter_mut().zip(&points) {
                *v = light_visibility(&field, p, l, settings);
            }
        });
    out
}

/// Visible fraction of one light from each of `cells` (row-major cell indices) of a height
/// field: [`visibilities`] for one light and some cells (the same values).
pub fn cell_visibilities(
    field: &HeightField,
    cells: &[usize],
    light: &Light,
    settings: ShadowSettings,
) -> Vec<f64> {
    let l = light_point(light);
    let g = field.grid;
    cells
        .par_iter()
        .map(|&c| {
            let p = [g.x_mm(c % g.nx), g.y_mm(c / g.nx), field.height_mm[c]];
            light_visibility(field, p, l, settings)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const GRID: Grid = Grid {
        nx: 200,
        ny: 40,
        cell_mm: 0.05,
    };

    fn light_at(x: f64, y: f64, z: f64) -> Light {
        Light {
            position_mm: [x, y, z],
            color: [1.0; 3],
            intensity: 1.0,
        }
    }

    fn hard(steps: u32) -> ShadowSettings {
        ShadowSettings {
            steps,
            max_march_mm: 20.0,
            led_radius_mm: 0.0,
        }
    }

    #[test]
    fn flat_gel_casts_no_shadow() {
        let uz = vec![0.0; GRID.len()];
        let lights = [light_at(12.0, 3.0, -3.0), light_at(-20.0, 0.0, -1.0)];
        let v = visibilities(&uz, GRID, &lights, ShadowSettings::default());
        assert!(v.iter().all(|&x| x == 1.0));
    }

    /// A plane tilted toward a distant light (its elevation slope 0.15 everywhere on the
    /// strip): shadowed iff the plane's slope exceeds 0.15, wherever on the plane.
    #[test]
    fn tilted_plane_is_shadowed_iff_steeper_than_the_light() {
        let light = light_at(5000.0, 0.0, -750.0);
        for (slope, lit) in [(0.10, true), (0.14, true), (0.16, false), (0.3, false)] {
            // Height s·x toward the light (u_z = −h); a margin keeps clamped samples away.
            let uz: Vec<f64> = (0..GRID.len())
                .map(|c| -slope * GRID.x_mm(c % GRID.nx))
                .collect();
            let v = visibilities(&uz, GRID, std::slice::from_ref(&light), hard(16));
            for c in (0..GRID.len()).filter(|c| c % GRID.nx < GRID.nx / 2) {
                assert_eq!(v[c], if lit { 1.0 } else { 0.0 }, "slope {slope} cell {c}");
            }
        }
    }

    /// A wall of height H at x = x_w casts a shadow on the flat gel behind it out to the
    /// distance where the ray toward the light clears its top: exact similar triangles.
    #[test]
    fn step_shadow_has_the_similar_triangle_length() {
        let wall_height = 0.3;
        let wall_from = 150; // cells with i ≥ 150 are raised
        let uz: Vec<f64> = (0..GRID.len())
            .map(|c| {
                if c % GRID.nx >= wall_from {
                    -wall_height
                } else {
                    0.0
                }
            })
            .collect();
        let (lx, lh) = (GRID.x_mm(wall_from) + 10.0, 2.0);
        let light = light_at(lx, 0.0, -lh);
        let v = visibilities(&uz, GRID, &[light], hard(400));
        // Heights ramp bilinearly over the cell before the wall, so its top edge is the centre
        // of the first raised cell; the ray from x passes it at height lh·d/(lx − x), d the
        // distance to the edge: shadowed iff that is below H.
        let x_top = GRID.x_mm(wall_from);
        let j = GRID.ny / 2;
        for i in 0..wall_from - 1 {
            let x = GRID.x_mm(i);
            let d = x_top - x;
            let ray_at_wall = lh * d / (lx - x);
            if (ray_at_wall - wall_height).abs() < 0.02 {
                continue; // within a cell's ramp of the edge
            }
            let expect = if ray_at_wall > wall_height { 1.0 } else { 0.0 };
            assert_eq!(
                v[j * GRID.nx + i],
                expect,
                "cell {i}, ray at wall {ray_at_wall}"
            );
        }
        // And the far side of the wall faces the light: lit.
        assert_eq!(v[j * GRID.nx + GRID.nx - 1], 1.0);
    }

    /// Mirror symmetry: a bump lit from +x and its mirror image lit from −x shadow mirror cells.
    #[test]
    fn shadows_mirror_with_the_scene() {
        let bump = |x: f64, y: f64| -0.4 * (-((x - 0.7).powi(2) + y * y) / 0.1).exp();
        let uz: Vec<f64> = (0..GRID.len())
            .map(|c| bump(GRID.x_mm(c % GRID.nx), GRID.y_mm(c / GRID.nx)))
            .collect();
        let mirrored: Vec<f64> = (0..GRID.len())
            .map(|c| bump(-GRID.x_mm(c % GRID.nx), GRID.y_mm(c / GRID.nx)))
            .collect();
        let s = ShadowSettings::default();
        let a = visibilities(&uz, GRID, &[light_at(-8.0, 1.0, -2.0)], s);
        let b = visibilities(&mirrored, GRID, &[light_at(8.0, 1.0, -2.0)], s);
        let mut shadowed = 0;
        for (c, va) in a.iter().enumerate() {
            let (i, j) = (c % GRID.nx, c / GRID.nx);
            let m = j * GRID.nx + (GRID.nx - 1 - i);
            assert!((va - b[m]).abs() < 1e-9, "cell {c}: {va} vs {}", b[m]);
            shadowed += usize::from(*va < 0.5);
        }
        assert!(shadowed > 20, "the bump casts a shadow ({shadowed} cells)");
    }

    /// Asserts that every cell's visibility of every light equals the full march's; returns
    /// the counts of fully lit and of (partly) shadowed rays.
    fn assert_shortcuts_exact(
        uz: &[f64],
        grid: Grid,
        lights: &[[f64; 3]],
        s: ShadowSettings,
    ) -> (usize, usize) {
        let field = HeightField::from_uz(uz, grid);
        let (mut lit, mut shadowed) = (0, 0);
        for &light in lights {
            for c in 0..grid.len() {
                let p = [
                    grid.x_mm(c % grid.nx),
                    grid.y_mm(c / grid.nx),
                    field.height_mm[c],
                ];
                let fast = visibility(&field, p, light, s, true);
                let full = visibility(&field, p, light, s, false);
                assert_eq!(
                    fast, full,
                    "{}×{} cell {c}, light {light:?}",
                    grid.nx, grid.ny
                );
                lit += usize::from(full == 1.0);
                shadowed += usize::from(full < 1.0);
            }
        }
        (lit, shadowed)
    }

    /// The tile shortcuts change nothing: every cell's visibility equals the full march's,
    /// over bumps of several sizes lit from several sides.
    #[test]
    fn the_tile_shortcut_is_exact() {
        let uz: Vec<f64> = (0..GRID.len())
            .map(|c| {
                let (x, y) = (GRID.x_mm(c % GRID.nx), GRID.y_mm(c / GRID.nx));
                -0.5 * (-((x - 1.0).powi(2) + y * y) / 0.3).exp()
                    - 0.2 * (-((x + 2.5).powi(2) + (y - 0.5).powi(2)) / 0.05).exp()
                    - 0.01 * (3.0 * x).sin()
            })
            .collect();
        let lights = [[9.0, 2.0, 2.5], [-7.0, -3.0, 1.5], [0.5, 9.0, 4.0]];
        let (lit, _) = assert_shortcuts_exact(&uz, GRID, &lights, ShadowSettings::default());
        assert!(lit > 1000 && lit < 3 * GRID.len(), "{lit}");
        // an odd step count with marches cut short by max_march_mm (the last sample counts)
        let odd = ShadowSettings {
            steps: 7,
            max_march_mm: 1.3,
            led_radius_mm: 0.5,
        };
        let (lit, shadowed) = assert_shortcuts_exact(&uz, GRID, &lights, odd);
        assert!(lit > 1000 && shadowed > 100, "{lit} {shadowed}");
    }

    /// The same on a calibration ball's Hertz surface under the GelSight 2017 LEDs, where the
    /// far field rises gently everywhere (the slope bound proves most rays lit).
    #[test]
    fn the_shortcuts_are_exact_on_a_ball_press() {
        // 8-cell tiles at 320 × 240 and 16-cell tiles at 640 × 480 over the same view
        for (nx, ny, cell_mm) in [(320, 240, 0.059), (640, 480, 0.0295)] {
            let grid = Grid { nx, ny, cell_mm };
            let uz = crate::ball::ball_press_uz_mm(grid, [1.0, -0.5], 1.2, 2.0).unwrap();
            let s = ShadowSettings {
                steps: 32,
                max_march_mm: 6.0,
                led_radius_mm: 1.0,
            };
            let lights = [[12.0, 0.0, 4.0], [-6.0, -10.39, 4.0], [-6.0, 10.39, 4.0]];
            let (lit, shadowed) = assert_shortcuts_exact(&uz, grid, &lights, s);
            assert!(shadowed > 50 && lit > 2 * grid.len(), "{shadowed} {lit}");
        }
    }

    /// One light at chosen cells gives the same values as every light at every cell.
    #[test]
    fn cell_visibilities_match_the_full_field() {
        let uz = crate::ball::ball_press_uz_mm(GRID, [0.5, 0.1], 0.8, 2.0).unwrap();
        let lights = [light_at(8.0, 1.0, -2.0), light_at(-6.0, -4.0, -3.0)];
        let all = visibilities(&uz, GRID, &lights, ShadowSettings::default());
        let field = HeightField::from_uz(&uz, GRID);
        let cells: Vec<usize> = (0..GRID.len()).step_by(7).collect();
        for (l, light) in lights.iter().enumerate() {
            let some = cell_visibilities(&field, &cells, light, ShadowSettings::default());
            for (v, &c) in some.iter().zip(&cells) {
                assert_eq!(*v, all[c * lights.len() + l], "cell {c}, light {l}");
            }
        }
        assert!(all.iter().any(|v| *v < 1.0), "the press casts a shadow");
    }

    #[test]
    fn penumbra_is_linear_across_the_disc() {
        assert_eq!(penumbra(0.0, 0.1), 0.5);
        assert_eq!(penumbra(0.1, 0.1), 1.0);
        assert_eq!(penumbra(-0.1, 0.1), 0.0);
        assert!((penumbra(0.05, 0.1) - 0.75).abs() < 1e-12);
    }
}
