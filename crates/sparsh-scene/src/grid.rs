//! The gel grid: cell centres in millimetres, in the sensor's camera frame.
//!
//! Frame: x along image columns, y along image rows (downwards in the image), z from the camera
//! through the gel towards the indenter (right-handed). The undeformed gel surface is z = 0; the
//! indenter lives at z > 0 and presses towards −z.

/// A regular grid of square cells centred on the sensor axis; row-major, index `j * nx + i`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Grid {
    /// Cells along x (image columns).
    pub nx: usize,
    /// Cells along y (image rows).
    pub ny: usize,
    /// Cell edge length (mm).
    pub cell_mm: f64,
}

impl Grid {
    /// Number of cells.
    pub fn len(&self) -> usize {
        self.nx * self.ny
    }

    /// True when the grid has no cells.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// x of the centre of column `i` (mm).
    pub fn x_mm(&self, i: usize) -> f64 {
        (i as f64 + 0.5 - self.nx as f64 / 2.0) * self.cell_mm
    }

    /// y of the centre of row `j` (mm).
    pub fn y_mm(&self, j: usize) -> f64 {
        (j as f64 + 0.5 - self.ny as f64 / 2.0) * self.cell_mm
    }

    /// Area of one cell (mm²).
    pub fn cell_area_mm2(&self) -> f64 {
        self.cell_mm * self.cell_mm
    }
}
