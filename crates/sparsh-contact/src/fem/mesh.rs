//! The gel block as a graded tensor-product grid of boxes: a uniform fine zone under the contact,
//! geometric growth away from it, fine layers at the surface and coarser ones towards the window.
//!
//! Nodes are numbered `i + nx (j + ny k)` with k = 0 on the surface (z = 0) and k = nz on the
//! window (z = −h), so the window's nodes, which are fixed, come last and the free degrees of
//! freedom are the first `3 nx ny nz`.

/// Node coordinates along one axis, ascending.
pub type Axis = Vec<f64>;

/// Coordinates from `lo` to `hi`: spacing `fine` on [fine_lo, fine_hi] (clipped to [lo, hi]),
/// growing by `growth` per element outside it.
pub fn graded_axis(lo: f64, hi: f64, fine_lo: f64, fine_hi: f64, fine: f64, growth: f64) -> Axis {
    let (a, b) = (fine_lo.max(lo), fine_hi.min(hi));
    let n = (((b - a) / fine).ceil() as usize).max(1);
    let mut core: Vec<f64> = (0..=n).map(|k| a + (b - a) * k as f64 / n as f64).collect();
    let step = (b - a) / n as f64;
    // Grows from `start` towards `end` (either direction); the last element absorbs the rest, or
    // is merged into its neighbour when that rest is under half a step.
    let grow = |start: f64, end: f64| -> Vec<f64> {
        let sign = (end - start).signum();
        let mut out = Vec::new();
        let mut x = start;
        let mut s = step;
        loop {
            s *= growth;
            let remaining = (end - x).abs();
            if remaining <= s * 1.5 {
                if remaining < 0.5 * s && !out.is_empty() {
                    out.pop();
                }
                out.push(end);
                break;
            }
            x += sign * s;
            out.push(x);
        }
        out
    };
    let mut left = if a > lo { grow(a, lo) } else { Vec::new() };
    left.reverse();
    let right = if b < hi { grow(b, hi) } else { Vec::new() };
    let mut axis = left;
    axis.append(&mut core);
    axis.extend(right);
    axis
}

/// Layer depths from the surface (0) down to −h: first layer `top`, growing by `growth` up to
/// h / `min_layers`, so at least `min_layers` layers.
pub fn graded_depth(h: f64, top: f64, growth: f64, min_layers: usize) -> Axis {
    let thickest = h / min_layers as f64;
    let top = top.min(thickest);
    let mut z = vec![0.0];
    let mut s = top;
    let mut depth = 0.0;
    loop {
        let remaining = h - depth;
        if remaining <= s * 1.5 {
            if remaining < 0.5 * s && z.len() > 1 {
                z.pop();
            }
            z.push(-h);
            break;
        }
        depth += s;
        z.push(-depth);
        s = (s * growth).min(thickest);
    }
    z
}

/// The structured mesh.
#[derive(Debug, Clone, PartialEq)]
pub struct Mesh {
    /// Node x (mm).
    pub x: Axis,
    /// Node y (mm).
    pub y: Axis,
    /// Node z (mm), from 0 down to −h.
    pub z: Axis,
    /// The fine zone [x0, x1] × [y0, y1] (mm) and its element size (mm).
    pub fine_zone: [f64; 4],
    /// Element size in the fine zone (mm).
    pub fine_mm: f64,
}

impl Mesh {
    /// Nodes along x, y, z.
    pub fn counts(&self) -> [usize; 3] {
        [self.x.len(), self.y.len(), self.z.len()]
    }

    /// Node index of (i, j, k).
    pub fn node(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.x.len() * (j + self.y.len() * k)
    }

    /// Number of free degrees of freedom (every node above the window, 3 each).
    pub fn free_dofs(&self) -> usize {
        3 * self.x.len() * self.y.len() * (self.z.len() - 1)
    }

    /// Number of nodes.
    pub fn nodes(&self) -> usize {
        self.x.len() * self.y.len() * self.z.len()
    }

    /// Number of elements.
    pub fn elements(&self) -> usize {
        (self.x.len() - 1) * (self.y.len() - 1) * (self.z.len() - 1)
    }

    /// Element (i, j, k)'s 8 node indices, local order ix + 2 iy + 4 iz with iz = 0 the lower
    /// face (larger k: z decreases with k).
    pub fn element_nodes(&self, i: usize, j: usize, k: usize) -> [usize; 8] {
        let mut out = [0; 8];
        for (a, o) in out.iter_mut().enumerate() {
            let (di, dj) = (a & 1, (a >> 1) & 1);
            // Local iz = 0 is the low-z face, i.e. node layer k + 1.
            let dk = 1 - ((a >> 2) & 1);
            *o = self.node(i + di, j + dj, k + dk);
        }
        out
    }

    /// Element (i, j, k)'s edge lengths.
    pub fn element_size(&self, i: usize, j: usize, k: usize) -> [f64; 3] {
        [
            self.x[i + 1] - self.x[i],
            self.y[j + 1] - self.y[j],
            self.z[k] - self.z[k + 1],
        ]
    }

    /// Surface node (i, j)'s tributary area (mm²).
    pub fn surface_area_mm2(&self, i: usize, j: usize) -> f64 {
        let half = |a: &Axis, i: usize| {
            let lo = if i > 0 { a[i] - a[i - 1] } else { 0.0 };
            let hi = if i + 1 < a.len() {
                a[i + 1] - a[i]
            } else {
                0.0
            };
            0.5 * (lo + hi)
        };
        half(&self.x, i) * half(&self.y, j)
    }

    /// Reference position of node `n`.
    pub fn position(&self, n: usize) -> [f64; 3] {
        let nx = self.x.len();
        let ny = self.y.len();
        [self.x[n % nx], self.y[(n / nx) % ny], self.z[n / (nx * ny)]]
    }

    /// The free degrees of freedom in nested-dissection order (George 1973; a geometric
    /// bisection, since the mesh is a tensor grid): the longest side of a block of nodes is cut
    /// by one plane of nodes, which no element crosses, both halves are ordered the same way
    /// and the plane comes after them. Entry `p` is the dof eliminated `p`-th. On the deep
    /// press's mesh the Cholesky factor has 25 % fewer nonzeros than under approximate minimum
    /// degree, and factorises in about half the time.
    pub fn nested_dissection(&self) -> Vec<usize> {
        let [nx, ny, nz] = self.counts();
        let mut order = Vec::with_capacity(self.free_dofs());
        dissect(self, [0, 0, 0], [nx, ny, nz - 1], &mut order);
        order
    }
}

/// Appends the dofs of the nodes in the block [lo, hi) in nested-dissection order.
fn dissect(mesh: &Mesh, lo: [usize; 3], hi: [usize; 3], order: &mut Vec<usize>) {
    let size = [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]];
    let axis = (0..3).max_by_key(|&a| (size[a], a)).expect("three axes");
    if size.iter().product::<usize>() <= 64 || size[axis] < 3 {
        for k in lo[2]..hi[2] {
            for j in lo[1]..hi[1] {
                for i in lo[0]..hi[0] {
                    let n = mesh.node(i, j, k);
                    order.extend([3 * n, 3 * n + 1, 3 * n + 2]);
                }
            }
        }
        return;
    }
    let cut = lo[axis] + size[axis] / 2;
    let (mut left_hi, mut right_lo) = (hi, lo);
    left_hi[axis] = cut;
    right_lo[axis] = cut + 1;
    dissect(mesh, lo, left_hi, order);
    dissect(mesh, right_lo, hi, order);
    let (mut plane_lo, mut plane_hi) = (lo, hi);
    plane_lo[axis] = cut;
    plane_hi[axis] = cut + 1;
    dissect(mesh, plane_lo, plane_hi, order);
}

/// The cell of `axis` holding `v` and the local coordinate in [0, 1] (clamped at the ends).
pub fn locate(axis: &[f64], v: f64) -> (usize, f64) {
    let n = axis.len();
    let i = axis.partition_point(|&a| a <= v).clamp(1, n - 1) - 1;
    let t = ((v - axis[i]) / (axis[i + 1] - axis[i])).clamp(0.0, 1.0);
    (i, t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn axes_cover_their_range_with_graded_steps() {
        let a = graded_axis(-10.0, 12.0, -1.0, 2.0, 0.1, 1.4);
        assert_eq!(a.first(), Some(&-10.0));
        assert_eq!(a.last(), Some(&12.0));
        assert!(a.windows(2).all(|w| w[1] > w[0]));
        let steps: Vec<f64> = a.windows(2).map(|w| w[1] - w[0]).collect();
        assert!(steps.iter().all(|s| (0.1 - 1e-9..12.0).contains(s)));
        // Neighbouring steps differ by at most the growth (and the merged last element).
        for w in steps.windows(2) {
            let r = w[1].max(w[0]) / w[1].min(w[0]);
            assert!(r < 2.6, "{r}");
        }
        let z = graded_depth(3.0, 0.1, 1.4, 4);
        assert_eq!((z[0], *z.last().unwrap()), (0.0, -3.0));
        assert!(z.len() >= 5 && z.windows(2).all(|w| w[1] < w[0]));
    }

    /// A 10 × 10 × 2 mm block with a fine zone off centre.
    fn small_mesh() -> Mesh {
        Mesh {
            x: graded_axis(-5.0, 5.0, -1.0, 1.0, 0.25, 1.5),
            y: graded_axis(-4.0, 6.0, -0.5, 1.5, 0.25, 1.5),
            z: graded_depth(2.0, 0.2, 1.5, 3),
            fine_zone: [-1.0, 1.0, -0.5, 1.5],
            fine_mm: 0.25,
        }
    }

    #[test]
    fn surface_areas_add_up_to_the_block_top() {
        let m = small_mesh();
        let total: f64 = (0..m.y.len())
            .flat_map(|j| (0..m.x.len()).map(move |i| (i, j)))
            .map(|(i, j)| m.surface_area_mm2(i, j))
            .sum();
        assert!((total - 100.0).abs() < 1e-9);
        assert_eq!(locate(&m.x, -5.0).0, 0);
        assert_eq!(locate(&m.x, 5.0).0, m.x.len() - 2);
    }

    #[test]
    fn nested_dissection_is_a_permutation_of_the_free_dofs() {
        let m = small_mesh();
        let mut order = m.nested_dissection();
        assert_eq!(order.len(), m.free_dofs());
        order.sort_unstable();
        assert!(order.iter().enumerate().all(|(p, &d)| p == d));
    }
}
