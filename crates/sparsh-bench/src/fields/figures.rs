//! Figures of tactile force fields in the manner of the Sparsh paper's force-field figure: the
//! normal field as a colour map (viridis) with the shear field as a quiver of white arrows over
//! it, laid out as a grid with one row per example ("press", "slide", "twist", …) and one column
//! per source ("ground truth", "self-supervised", "supervised", "Farnebäck", …).
//!
//! Conventions: fields are `height × width`, row-major; shear `[x, y]` is in pixels of the
//! field, x along columns (right) and y along rows (down), as in images. Each panel is scaled on
//! its own: the normal field to its `[0, max]` (the maximum is printed under the title), the
//! arrows so that the panel's 95th-percentile shear magnitude spans 1.5 grid spacings (the key
//! under the title shows an arrow of that length and the shear it stands for). Non-finite values
//! count as 0, and so do negative normal values.

use std::ops::Range;
use std::path::Path;

use base64::Engine;
use base64::engine::general_purpose::STANDARD;
use plotters::coord::Shift;
use sparsh_data::encode_png;

use crate::io::{SANS, register_sans, write_atomic};
use plotters::prelude::*;
use plotters::style::FontTransform;
use plotters::style::text_anchor::{HPos, Pos, VPos};

/// Height of a panel in the figure, in figure pixels (unless its width would pass the cap).
const PANEL_H: f64 = 240.0;
/// Widest panel, in figure pixels: very wide fields are scaled down to it.
const PANEL_W_MAX: f64 = 960.0;
/// Arrows across a panel (fewer when the field has fewer columns).
const ARROWS_ACROSS: usize = 12;
/// Length of an arrow at the panel's 95th-percentile shear, in grid spacings.
const P95_SPACINGS: f64 = 1.5;
/// Closest grid spacing, in figure pixels (narrow panels get fewer arrows across).
const MIN_SPACING_PX: f64 = 16.0;
/// Shorter arrows are not drawn (they would be a dot).
const MIN_ARROW_PX: f64 = 3.0;
/// Figure margin, width of the row-label column, title block above panels, gap between cells.
const MARGIN: i32 = 10;
const LABEL_W: i32 = 34;
const TITLE_H: i32 = 42;
const GAP: i32 = 14;
/// Narrowest caption under a title, in figure pixels.
const CAPTION_W: i32 = 180;

/// Control points of matplotlib's viridis at 0, 0.1, …, 1, interpolated linearly in sRGB.
const VIRIDIS: [[u8; 3]; 11] = [
    [68, 1, 84],
    [72, 36, 117],
    [65, 68, 135],
    [53, 95, 141],
    [42, 120, 142],
    [33, 145, 140],
    [34, 168, 132],
    [68, 191, 112],
    [122, 209, 81],
    [189, 223, 38],
    [253, 231, 37],
];

/// One panel: a scalar field (normal) and optionally a 2-D vector field (shear, in pixels), both
/// `height × width` row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    /// Title drawn above the panel (the source, e.g. "ground truth").
    pub title: String,
    /// Rows of the fields.
    pub height: usize,
    /// Columns of the fields.
    pub width: usize,
    /// Normal field, `height × width` values, row-major; shown normalised to its own `[0, max]`.
    pub normal: Vec<f32>,
    /// Shear field in pixels, `[x (right), y (down)]`, `height × width` vectors, row-major.
    pub shear_px: Option<Vec<[f32; 2]>>,
}

/// Writes a grid of panels (`rows[r][c]`, every row the same length) to `path` as PNG (and SVG
/// when the extension is .svg) with row labels on the left.
///
/// A `.png` path gets the PNG; a `.svg` path gets the SVG and the same figure as PNG beside it
/// (`path` with the extension `.png`); any other extension is an error. `row_labels` has one
/// label per row. Files are written to a temporary name and renamed into place. Errors are one
/// line naming the file, and the panel at fault when there is one.
pub fn write_field_grid(
    path: &Path,
    row_labels: &[String],
    rows: &[Vec<Panel>],
) -> Result<(), String> {
    let at = |msg: String| format!("{}: {msg}", path.display());
    let svg = match path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .as_deref()
    {
        Some("png") => false,
        Some("svg") => true,
        _ => return Err(at("the figure must be a .png or .svg file".into())),
    };
    let cols = rows.first().map_or(0, Vec::len);
    if cols == 0 {
        return Err(at("no panels to draw".into()));
    }
    if row_labels.len() != rows.len() {
        return Err(at(format!(
            "{} row labels for {} rows",
            row_labels.len(),
            rows.len()
        )));
    }
    let mut grid = Vec::with_capacity(rows.len());
    for (r, (label, row)) in row_labels.iter().zip(rows).enumerate() {
        if row.len() != cols {
            return Err(at(format!(
                "row {} ({label:?}) has {} panels, row 1 has {cols}",
                r + 1,
                row.len()
            )));
        }
        let prepared: Result<Vec<Prepared>, String> = row
            .iter()
            .enumerate()
            .map(|(c, p)| {
                prepare(p).map_err(|e| {
                    at(format!(
                        "panel {:?} (row {label:?}, column {}): {e}",
                        p.title,
                        c + 1
                    ))
                })
            })
            .collect();
        grid.push(prepared?);
    }
    let layout = Layout::new(&grid);
    let (w, h) = (layout.width, layout.height);

    let png_path = if svg {
        path.with_extension("png")
    } else {
        path.to_path_buf()
    };
    let mut rgb = vec![255u8; w as usize * h as usize * 3];
    for (r, row) in grid.iter().enumerate() {
        for (c, p) in row.iter().enumerate() {
            let (x0, y0) = layout.panel_origin(r, c, p);
            let (pw, ph) = (p.size.0 as usize, p.size.1 as usize);
            for y in 0..ph {
                let dst = ((y0 as usize + y) * w as usize + x0 as usize) * 3;
                rgb[dst..dst + pw * 3].copy_from_slice(&p.rgb[y * pw * 3..(y + 1) * pw * 3]);
            }
        }
    }
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        draw_overlay(&root, &layout, row_labels, &grid).map_err(&at)?;
        root.present().map_err(|e| at(format!("drawing: {e}")))?;
    }
    let img = image::RgbImage::from_raw(w, h, rgb).ok_or_else(|| at("image buffer size".into()))?;
    write_atomic(&png_path, &encode_png(&img).map_err(&at)?).map_err(|e| e.to_string())?;

    if svg {
        let mut text = String::new();
        {
            let root = SVGBackend::with_string(&mut text, (w, h)).into_drawing_area();
            draw_overlay(&root, &layout, row_labels, &grid).map_err(&at)?;
            root.present().map_err(|e| at(format!("drawing: {e}")))?;
        }
        let text = with_heatmaps(&text, &layout, &grid).map_err(&at)?;
        write_atomic(path, text.as_bytes()).map_err(|e| e.to_string())?;
    }
    Ok(())
}

/// A panel checked and rendered: the colour map at figure size and the arrows.
struct Prepared<'a> {
    title: &'a str,
    /// Width and height in figure pixels.
    size: (u32, u32),
    /// The coloured normal field, `size.0 × size.1` RGB.
    rgb: Vec<u8>,
    /// Largest normal value (0 when the field is nowhere positive).
    max: f32,
    quiver: Quiver,
}

enum Quiver {
    /// No shear field given.
    Absent,
    /// A shear field that is zero everywhere.
    Zero,
    /// Arrows in panel pixels; `p95` is the shear that spans `P95_SPACINGS × spacing` pixels.
    Arrows {
        p95: f32,
        spacing: f64,
        arrows: Vec<Arrow>,
    },
}

/// An arrow in panel pixels, centred on its grid point.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Arrow {
    tail: (f64, f64),
    tip: (f64, f64),
}

fn clean(v: f32) -> f32 {
    if v.is_finite() { v } else { 0.0 }
}

/// The input indices that output index `i` of `n_out` covers when `n_in` values are resampled:
/// a box average when shrinking, the nearest value when enlarging.
fn span(i: usize, n_out: usize, n_in: usize) -> Range<usize> {
    let a = i * n_in / n_out;
    a..((i + 1) * n_in / n_out).clamp(a + 1, n_in)
}

fn viridis(t: f32) -> [u8; 3] {
    let t = clean(t).clamp(0.0, 1.0);
    let x = t * (VIRIDIS.len() - 1) as f32;
    let i = (x.floor() as usize).min(VIRIDIS.len() - 2);
    let f = x - i as f32;
    let (a, b) = (VIRIDIS[i], VIRIDIS[i + 1]);
    std::array::from_fn(|k| {
        (f32::from(a[k]) + f * (f32::from(b[k]) - f32::from(a[k]))).round() as u8
    })
}

fn prepare(p: &Panel) -> Result<Prepared<'_>, String> {
    let (h, w) = (p.height, p.width);
    if h == 0 || w == 0 {
        return Err(format!("empty field ({h} × {w})"));
    }
    let n = h
        .checked_mul(w)
        .ok_or_else(|| format!("field too large ({h} × {w})"))?;
    if p.normal.len() != n {
        return Err(format!(
            "normal has {} values, expected {h} × {w} = {n}",
            p.normal.len()
        ));
    }
    if let Some(s) = &p.shear_px
        && s.len() != n
    {
        return Err(format!(
            "shear has {} vectors, expected {h} × {w} = {n}",
            s.len()
        ));
    }
    let scale = (PANEL_H / h as f64).min(PANEL_W_MAX / w as f64);
    let pw = ((w as f64 * scale).round() as usize).max(1);
    let ph = ((h as f64 * scale).round() as usize).max(1);

    let normal: Vec<f32> = p.normal.iter().map(|&v| clean(v).max(0.0)).collect();
    let max = normal.iter().copied().fold(0.0f32, f32::max);
    let inv = if max > 0.0 { 1.0 / max } else { 0.0 };
    let xs: Vec<Range<usize>> = (0..pw).map(|x| span(x, pw, w)).collect();
    let mut rgb = Vec::with_capacity(pw * ph * 3);
    for y in 0..ph {
        let ys = span(y, ph, h);
        for xr in &xs {
            let mut sum = 0.0f32;
            for row in ys.clone() {
                sum += normal[row * w + xr.start..row * w + xr.end]
                    .iter()
                    .sum::<f32>();
            }
            let mean = sum / (ys.len() * xr.len()) as f32;
            rgb.extend_from_slice(&viridis(mean * inv));
        }
    }
    let quiver = match &p.shear_px {
        None => Quiver::Absent,
        Some(s) => quiver(h, w, s, (pw as f64, ph as f64)),
    };
    Ok(Prepared {
        title: &p.title,
        size: (pw as u32, ph as u32),
        rgb,
        max,
        quiver,
    })
}

/// Arrows on a regular grid (`ARROWS_ACROSS` across, fewer when the field has fewer columns or
/// the spacing would be under `MIN_SPACING_PX`; square cells as far as the rows allow),
/// each the mean shear of its cell, scaled so the 95th percentile of the nonzero per-pixel
/// magnitudes spans `P95_SPACINGS` grid spacings. Zeros are left out of the percentile so that a
/// small contact patch on an otherwise still pad still gets readable arrows.
fn quiver(h: usize, w: usize, shear: &[[f32; 2]], (pw, ph): (f64, f64)) -> Quiver {
    let shear: Vec<[f32; 2]> = shear.iter().map(|v| [clean(v[0]), clean(v[1])]).collect();
    let mut mags: Vec<f32> = shear
        .iter()
        .map(|v| v[0].hypot(v[1]))
        .filter(|&m| m > 0.0)
        .collect();
    if mags.is_empty() {
        return Quiver::Zero;
    }
    let k = ((0.95 * mags.len() as f64).ceil() as usize).clamp(1, mags.len()) - 1;
    let p95 = *mags.select_nth_unstable_by(k, f32::total_cmp).1;
    let nx = ARROWS_ACROSS
        .min(w)
        .min(((pw / MIN_SPACING_PX) as usize).max(1));
    let spacing = pw / nx as f64;
    let ny = ((ph / spacing).round() as usize).clamp(1, h);
    let gain = P95_SPACINGS * spacing / f64::from(p95);
    let mut arrows = Vec::with_capacity(nx * ny);
    for j in 0..ny {
        let rows = span(j, ny, h);
        for i in 0..nx {
            let cols = span(i, nx, w);
            let (mut sx, mut sy) = (0.0f64, 0.0f64);
            for r in rows.clone() {
                for v in &shear[r * w + cols.start..r * w + cols.end] {
                    sx += f64::from(v[0]);
                    sy += f64::from(v[1]);
                }
            }
            let cells = (rows.len() * cols.len()) as f64;
            let (dx, dy) = (gain * sx / cells, gain * sy / cells);
            if dx.hypot(dy) < MIN_ARROW_PX {
                continue;
            }
            let c = (
                (i as f64 + 0.5) * pw / nx as f64,
                (j as f64 + 0.5) * ph / ny as f64,
            );
            arrows.push(Arrow {
                tail: (c.0 - dx / 2.0, c.1 - dy / 2.0),
                tip: (c.0 + dx / 2.0, c.1 + dy / 2.0),
            });
        }
    }
    Quiver::Arrows {
        p95,
        spacing,
        arrows,
    }
}

/// Where the cells and panels go: a column is as wide as its widest panel, a row as tall as its
/// tallest one, and each panel is centred in its cell.
struct Layout {
    /// Left edge and width of each column.
    cols: Vec<(i32, i32)>,
    /// Top edge (of the title block) and field height of each row.
    rows: Vec<(i32, i32)>,
    width: u32,
    height: u32,
}

impl Layout {
    fn new(grid: &[Vec<Prepared>]) -> Self {
        let ncols = grid.first().map_or(0, Vec::len);
        let mut cols = Vec::with_capacity(ncols);
        let mut x = MARGIN + LABEL_W;
        for c in 0..ncols {
            let w = grid.iter().map(|row| row[c].size.0).max().unwrap_or(1) as i32;
            cols.push((x, w));
            x += w + GAP;
        }
        let mut rows = Vec::with_capacity(grid.len());
        let mut y = MARGIN;
        for row in grid {
            let h = row.iter().map(|p| p.size.1).max().unwrap_or(1) as i32;
            rows.push((y, h));
            y += TITLE_H + h + GAP;
        }
        Layout {
            cols,
            rows,
            width: (x - GAP + MARGIN) as u32,
            height: (y - GAP + MARGIN) as u32,
        }
    }

    /// Left, top, width and field height of cell `(r, c)`; the top is that of the title block.
    fn cell(&self, r: usize, c: usize) -> (i32, i32, i32, i32) {
        let ((x, w), (y, h)) = (self.cols[c], self.rows[r]);
        (x, y, w, h)
    }

    /// Top-left corner of the field of panel `p` at `(r, c)`.
    fn panel_origin(&self, r: usize, c: usize, p: &Prepared) -> (i32, i32) {
        let (x, y, w, h) = self.cell(r, c);
        (
            x + (w - p.size.0 as i32) / 2,
            y + TITLE_H + (h - p.size.1 as i32) / 2,
        )
    }
}

/// A number with about three significant digits.
fn short(v: f32) -> String {
    let a = v.abs();
    if a == 0.0 {
        "0".into()
    } else if !(1e-2..1e4).contains(&a) {
        format!("{v:.2e}")
    } else if a >= 100.0 {
        format!("{v:.0}")
    } else if a >= 10.0 {
        format!("{v:.1}")
    } else if a >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

fn draw_err(e: impl std::fmt::Display) -> String {
    format!("drawing: {e}")
}

/// The largest font size up to `size` at which `text` is at most `room` pixels long.
fn fitted<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    text: &str,
    size: f64,
    room: i32,
) -> f64 {
    let mut size = size;
    while size > 8.0
        && root
            .estimate_text_size(text, &TextStyle::from((SANS, size).into_font()))
            .is_ok_and(|(w, _)| w as i32 > room)
    {
        size -= 1.0;
    }
    size
}

fn label<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    text: &str,
    at: (i32, i32),
    style: TextStyle,
) -> Result<(), String> {
    root.draw(&Text::new(text.to_string(), at, style))
        .map_err(draw_err)
}

/// Titles, captions, row labels and arrows; the colour maps are put in by the caller (pixels in
/// the PNG, embedded images in the SVG), so the background is left alone here.
fn draw_overlay<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    layout: &Layout,
    row_labels: &[String],
    grid: &[Vec<Prepared>],
) -> Result<(), String> {
    register_sans().map_err(|e| e.to_string())?;
    let grey = RGBColor(70, 70, 70);
    for (r, (name, row)) in row_labels.iter().zip(grid).enumerate() {
        let (_, y, _, cell_h) = layout.cell(r, 0);
        let size = fitted(root, name, 18.0, cell_h);
        let style = (SANS, size)
            .into_font()
            .color(&BLACK)
            .pos(Pos::new(HPos::Center, VPos::Center))
            .transform(FontTransform::Rotate270);
        label(
            root,
            name,
            (MARGIN + LABEL_W / 2, y + TITLE_H + cell_h / 2),
            style,
        )?;
        for (c, p) in row.iter().enumerate() {
            let (cx, cy, cw, _) = layout.cell(r, c);
            let (px, py) = layout.panel_origin(r, c, p);
            let (pw, ph) = (p.size.0 as i32, p.size.1 as i32);
            let size = fitted(root, p.title, 16.0, cw);
            let style = (SANS, size)
                .into_font()
                .color(&BLACK)
                .pos(Pos::new(HPos::Center, VPos::Top));
            label(root, p.title, (cx + cw / 2, cy + 2), style)?;

            // The caption spans the field, or CAPTION_W when the field is narrower.
            let span = pw.max(CAPTION_W.min(cw));
            let left_x = (px + pw / 2 - span / 2).clamp(cx, cx + cw - span);
            let right_x = left_x + span;
            let caption_y = cy + 24;
            let small = (SANS, 12.0).into_font().color(&grey);
            let left = small.pos(Pos::new(HPos::Left, VPos::Top));
            label(
                root,
                &format!("max {}", short(p.max)),
                (left_x, caption_y),
                left,
            )?;
            let right = small.pos(Pos::new(HPos::Right, VPos::Top));
            match &p.quiver {
                Quiver::Absent => {}
                Quiver::Zero => label(root, "no shear", (right_x, caption_y), right)?,
                Quiver::Arrows {
                    p95,
                    spacing,
                    arrows,
                } => {
                    let text = format!("{} px", short(*p95));
                    label(root, &text, (right_x, caption_y), right)?;
                    let tw = root.estimate_text_size(&text, &small).map_err(draw_err)?.0 as f64;
                    let end = f64::from(right_x) - tw - 5.0;
                    let y = f64::from(caption_y) + 5.0;
                    let key = Arrow {
                        tail: (end - P95_SPACINGS * spacing, y),
                        tip: (end, y),
                    };
                    draw_arrow(root, &key, (0.0, 0.0), None, Stroke::Plain(BLACK))?;
                    let bounds = Some((f64::from(pw - 1), f64::from(ph - 1)));
                    let origin = (f64::from(px), f64::from(py));
                    for pass in [Stroke::Outline, Stroke::Plain(WHITE)] {
                        for a in arrows {
                            draw_arrow(root, a, origin, bounds, pass)?;
                        }
                    }
                }
            }
        }
    }
    Ok(())
}

#[derive(Clone, Copy)]
enum Stroke {
    /// A black border under a white arrow.
    Outline,
    /// The arrow itself, one pixel wide.
    Plain(RGBColor),
}

/// Clips the segment `p`–`q` to `[0, w] × [0, h]` (Liang–Barsky).
fn clip(p: (f64, f64), q: (f64, f64), (w, h): (f64, f64)) -> Option<((f64, f64), (f64, f64))> {
    let (dx, dy) = (q.0 - p.0, q.1 - p.1);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (pk, qk) in [(-dx, p.0), (dx, w - p.0), (-dy, p.1), (dy, h - p.1)] {
        if pk == 0.0 {
            if qk < 0.0 {
                return None;
            }
        } else {
            let t = qk / pk;
            if pk < 0.0 {
                t0 = t0.max(t);
            } else {
                t1 = t1.min(t);
            }
        }
    }
    (t0 <= t1).then_some({
        (
            (p.0 + t0 * dx, p.1 + t0 * dy),
            (p.0 + t1 * dx, p.1 + t1 * dy),
        )
    })
}

/// Draws one arrow offset by `origin`, clipped to `bounds` (panel pixels) when given: the shaft
/// is cut at the edge and the head left out unless it fits whole.
fn draw_arrow<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    a: &Arrow,
    origin: (f64, f64),
    bounds: Option<(f64, f64)>,
    stroke: Stroke,
) -> Result<(), String> {
    let (dx, dy) = (a.tip.0 - a.tail.0, a.tip.1 - a.tail.1);
    let len = dx.hypot(dy);
    if len == 0.0 {
        return Ok(());
    }
    let (ux, uy) = (dx / len, dy / len);
    let head_len = (0.35 * len).clamp(3.0, 7.0).min(len);
    let half = 0.5 * head_len;
    let base = (a.tip.0 - ux * head_len, a.tip.1 - uy * head_len);
    let head = [
        a.tip,
        (base.0 - uy * half, base.1 + ux * half),
        (base.0 + uy * half, base.1 - ux * half),
    ];
    let inside = |q: &(f64, f64)| {
        bounds.is_none_or(|(w, h)| (0.0..=w).contains(&q.0) && (0.0..=h).contains(&q.1))
    };
    let head_fits = head.iter().all(inside);
    let shaft_end = if head_fits { base } else { a.tip };
    let shaft = match bounds {
        Some(b) => clip(a.tail, shaft_end, b),
        None => Some((a.tail, shaft_end)),
    };
    let px = |q: (f64, f64)| {
        (
            (q.0 + origin.0).round() as i32,
            (q.1 + origin.1).round() as i32,
        )
    };
    let (colour, width) = match stroke {
        Stroke::Outline => (BLACK, 3),
        Stroke::Plain(c) => (c, 1),
    };
    if let Some((s, e)) = shaft {
        root.draw(&PathElement::new(
            vec![px(s), px(e)],
            colour.stroke_width(width),
        ))
        .map_err(draw_err)?;
    }
    if head_fits {
        let pts: Vec<(i32, i32)> = head.iter().map(|&q| px(q)).collect();
        root.draw(&Polygon::new(pts.clone(), colour.filled()))
            .map_err(draw_err)?;
        if let Stroke::Outline = stroke {
            let mut ring = pts;
            ring.push(ring[0]);
            root.draw(&PathElement::new(ring, BLACK.stroke_width(2)))
                .map_err(draw_err)?;
        }
    }
    Ok(())
}

/// Puts a white background and the colour maps (as embedded PNG images) under what plotters drew.
fn with_heatmaps(svg: &str, layout: &Layout, grid: &[Vec<Prepared>]) -> Result<String, String> {
    let (header, rest) = svg
        .split_once('\n')
        .filter(|(h, _)| h.starts_with("<svg") && h.ends_with('>'))
        .ok_or("unexpected SVG from plotters")?;
    let mut out = String::with_capacity(svg.len());
    out.push_str(&header[..header.len() - 1]);
    out.push_str(" xmlns:xlink=\"http://www.w3.org/1999/xlink\">\n");
    out.push_str(&format!(
        "<rect x=\"0\" y=\"0\" width=\"{}\" height=\"{}\" fill=\"#FFFFFF\"/>\n",
        layout.width, layout.height
    ));
    for (r, row) in grid.iter().enumerate() {
        for (c, p) in row.iter().enumerate() {
            let (x, y) = layout.panel_origin(r, c, p);
            let img = image::RgbImage::from_raw(p.size.0, p.size.1, p.rgb.clone())
                .ok_or("image buffer size")?;
            out.push_str(&format!(
                "<image x=\"{x}\" y=\"{y}\" width=\"{}\" height=\"{}\" \
                 preserveAspectRatio=\"none\" xlink:href=\"data:image/png;base64,{}\"/>\n",
                p.size.0,
                p.size.1,
                STANDARD.encode(encode_png(&img)?)
            ));
        }
    }
    out.push_str(rest);
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    /// A fresh directory under the system temp dir, unique to this process and test.
    fn scratch(test: &str) -> PathBuf {
        let dir =
            std::env::temp_dir().join(format!("sparsh-fieldfig-{}-{test}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// A Gaussian bump of normal load with a swirl of shear around it.
    fn bump(title: &str, h: usize, w: usize) -> Panel {
        let (cy, cx) = (h as f32 / 2.0, w as f32 / 2.0);
        let mut normal = Vec::with_capacity(h * w);
        let mut shear = Vec::with_capacity(h * w);
        for y in 0..h {
            for x in 0..w {
                let (dx, dy) = (x as f32 + 0.5 - cx, y as f32 + 0.5 - cy);
                let g = (-(dx * dx + dy * dy) / 40.0).exp();
                normal.push(g);
                shear.push([-dy * g, dx * g]);
            }
        }
        Panel {
            title: title.into(),
            height: h,
            width: w,
            normal,
            shear_px: Some(shear),
        }
    }

    fn labels(names: &[&str]) -> Vec<String> {
        names.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn two_by_three_grid_is_a_png_of_the_expected_size() {
        let dir = scratch("grid");
        let rows: Vec<Vec<Panel>> = (0..2)
            .map(|_| ["a", "b", "c"].map(|t| bump(t, 24, 32)).to_vec())
            .collect();
        let path = dir.join("grid.png");
        write_field_grid(&path, &labels(&["press", "slide"]), &rows).unwrap();
        let img = image::open(&path).unwrap();
        // 24 × 32 fields are drawn 240 × 320.
        let w = 2 * MARGIN + LABEL_W + 3 * 320 + 2 * GAP;
        let h = 2 * MARGIN + 2 * (TITLE_H + 240) + GAP;
        assert_eq!((img.width(), img.height()), (w as u32, h as u32));
        let leftovers: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .filter(|n| n != "grid.png")
            .collect();
        assert!(leftovers.is_empty(), "{leftovers:?}");

        let svg = dir.join("grid.svg");
        write_field_grid(&svg, &labels(&["press", "slide"]), &rows).unwrap();
        let text = std::fs::read_to_string(&svg).unwrap();
        assert!(text.starts_with("<svg"));
        assert_eq!(text.matches("data:image/png;base64,").count(), 6);
        assert!(text.contains("press\n</text>") && text.contains("slide\n</text>"));
        assert_eq!(image::open(dir.join("grid.png")).unwrap().width(), w as u32);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn bad_input_is_a_one_line_error_naming_the_panel() {
        let dir = scratch("errors");
        let path = dir.join("bad.png");
        let mut short_normal = bump("supervised", 8, 8);
        short_normal.normal.pop();
        let rows = vec![vec![bump("ground truth", 8, 8), short_normal]];
        let e = write_field_grid(&path, &labels(&["press"]), &rows).unwrap_err();
        assert!(
            e.contains("\"supervised\"") && e.contains("normal has 63 values"),
            "{e}"
        );
        assert!(!e.contains('\n'));

        let mut short_shear = bump("Farne\nbäck", 8, 8);
        short_shear.shear_px.as_mut().unwrap().truncate(10);
        let e = write_field_grid(&path, &labels(&["twist"]), &[vec![short_shear]]).unwrap_err();
        assert!(
            e.contains("Farne\\nbäck") && e.contains("shear has 10"),
            "{e}"
        );
        assert!(!e.contains('\n'));

        let one = || vec![bump("a", 4, 4)];
        let empty: &[Vec<Panel>] = &[];
        assert!(write_field_grid(&path, &[], empty).is_err());
        assert!(write_field_grid(&path, &labels(&["x"]), &[vec![]]).is_err());
        let ragged = [one(), vec![bump("a", 4, 4), bump("b", 4, 4)]];
        let e = write_field_grid(&path, &labels(&["x", "y"]), &ragged).unwrap_err();
        assert!(e.contains("row 2") && !e.contains('\n'), "{e}");
        assert!(write_field_grid(&path, &labels(&["x", "y"]), &[one()]).is_err());
        assert!(write_field_grid(&dir.join("bad.jpg"), &labels(&["x"]), &[one()]).is_err());
        let mut flat = bump("flat", 4, 4);
        flat.height = 0;
        assert!(write_field_grid(&path, &labels(&["x"]), &[vec![flat]]).is_err());
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn colour_map_lands_where_the_normal_field_is() {
        let dir = scratch("orientation");
        // 10 rows × 20 columns (drawn 240 × 480), loaded only in the top-right corner.
        let (h, w) = (10, 20);
        let mut normal = vec![0.0f32; h * w];
        for y in 0..3 {
            for x in 15..20 {
                normal[y * w + x] = 2.5;
            }
        }
        normal[9 * w] = f32::NAN;
        let loaded = Panel {
            title: "loaded".into(),
            height: h,
            width: w,
            normal,
            shear_px: None,
        };
        let still = Panel {
            title: "still".into(),
            height: h,
            width: w,
            normal: vec![0.0; h * w],
            shear_px: Some(vec![[0.0, f32::NAN]; h * w]),
        };
        let path = dir.join("orient.png");
        write_field_grid(&path, &labels(&["press"]), &[vec![loaded, still]]).unwrap();
        let img = image::open(&path).unwrap().to_rgb8();
        let (x0, y0) = (MARGIN + LABEL_W, MARGIN + TITLE_H);
        // Centre of field pixel (row, column) of panel `c`; each field pixel is 24 figure pixels.
        let at = |c: i32, row: i32, col: i32| {
            let x = x0 + c * (480 + GAP) + col * 24 + 12;
            img.get_pixel(x as u32, (y0 + row * 24 + 12) as u32).0
        };
        assert_eq!(at(0, 1, 17), [253, 231, 37]);
        for (row, col) in [(1, 2), (8, 17), (8, 2), (9, 0), (5, 10)] {
            assert_eq!(at(0, row, col), [68, 1, 84], "({row}, {col})");
        }
        for (row, col) in [(1, 17), (5, 10), (9, 0)] {
            assert_eq!(at(1, row, col), [68, 1, 84], "still ({row}, {col})");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn arrows_point_along_the_shear_at_the_p95_scale() {
        let (h, w) = (24, 36);
        let right = quiver(h, w, &vec![[2.0, 0.0]; h * w], (360.0, 240.0));
        let Quiver::Arrows {
            p95,
            spacing,
            arrows,
        } = right
        else {
            panic!("no arrows");
        };
        assert_eq!(p95, 2.0);
        assert_eq!(spacing, 30.0);
        assert_eq!(arrows.len(), 12 * 8);
        for a in &arrows {
            assert!((a.tip.0 - a.tail.0 - 45.0).abs() < 1e-9 && a.tip.1 == a.tail.1);
        }
        // Down the rows: y grows downwards.
        let Quiver::Arrows { arrows, .. } = quiver(h, w, &vec![[0.0, 0.5]; h * w], (360.0, 240.0))
        else {
            panic!("no arrows");
        };
        assert!(
            arrows
                .iter()
                .all(|a| a.tip.1 > a.tail.1 && a.tip.0 == a.tail.0)
        );
        assert!(matches!(
            quiver(h, w, &vec![[0.0, 0.0]; h * w], (360.0, 240.0)),
            Quiver::Zero
        ));
        assert_eq!(
            clip((-10.0, 5.0), (20.0, 5.0), (10.0, 10.0)),
            Some(((0.0, 5.0), (10.0, 5.0)))
        );
        assert_eq!(clip((-10.0, 5.0), (-1.0, 5.0), (10.0, 10.0)), None);
    }

    #[test]
    fn helpers() {
        assert_eq!(viridis(0.0), VIRIDIS[0]);
        assert_eq!(viridis(f32::NAN), VIRIDIS[0]);
        assert_eq!(viridis(1.0), VIRIDIS[10]);
        assert_eq!(viridis(0.5), VIRIDIS[5]);
        assert_eq!(span(3, 10, 5), 1..2);
        assert_eq!(span(1, 5, 10), 2..4);
        assert_eq!(short(0.8), "0.800");
        assert_eq!(short(12.34), "12.3");
    }
}
