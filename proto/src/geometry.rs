//! Arena geometry and the grid-cell rules of REFERENCE.md §1.1–1.2.
//!
//! Both the world (which registers objects) and the agents (which reason about obstacle
//! footprints) need the exact same integer arithmetic, so it lives in the contract.
use crate::limits::{MAX_ARENA_SIDE, MAX_CELLS};
use serde::{Deserialize, Serialize};

/// An integer position; the origin is the centre of the arena.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
pub struct Pos {
    pub x: i32,
    pub y: i32,
}

impl Pos {
    pub const fn new(x: i32, y: i32) -> Self {
        Pos { x, y }
    }
}

/// 0-based, row-major cell index (the reference's 1-based id minus one).
pub type CellIdx = u32;

/// Arena width/height and grid size. Validated on construction, and when decoded (a
/// geometry also arrives over the network, in the world's run information): (W/2) and
/// (H/2) must be multiples of the grid size, as the reference requires; W and H at most
/// [`MAX_ARENA_SIDE`], at most [`MAX_CELLS`] cells. Within these limits every cell index
/// and coordinate product below fits in `i32`. (Before decoding checked, a grid of 0 in
/// the run information made a joining agent process divide by zero at its first cell
/// look-up: found by `geese-fuzz`, target `run_info`.)
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "GeometryFields")]
pub struct Geometry {
    /// Read through [`Geometry::width`], [`Geometry::height`] and [`Geometry::grid`]:
    /// the fields below are derived from them.
    width: i32,
    height: i32,
    grid: i32,
    /// Derived in [`Geometry::new`] (not encoded): every agent and object look-up of
    /// every step divides by the grid and by the number of columns, and a multiply by
    /// a precomputed reciprocal ([`Divisor`]) costs a fraction of a division.
    #[serde(skip_serializing)]
    cols: Divisor,
    #[serde(skip_serializing)]
    rows: i32,
    #[serde(skip_serializing)]
    by_grid: Divisor,
}

/// Division of a non-negative `i32` below 2²⁴ by a fixed divisor `d` in [1, 2²⁴) by a
/// multiply and a shift: with `m = ⌈2⁴⁰ / d⌉`, `⌊n·m / 2⁴⁰⌋ = ⌊n / d⌋` whenever
/// `n·d < 2⁴⁰` (the error of `m`, under `d / 2⁴⁰` per unit of `n`, cannot reach the
/// next multiple of `d`). Geometries keep coordinates below 10⁴ and cell indices below
/// 10⁶ ([`MAX_ARENA_SIDE`], [`MAX_CELLS`]), far inside that.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Divisor {
    d: i32,
    m: u64,
}

impl Divisor {
    const SHIFT: u32 = 40;
    fn new(d: i32) -> Divisor {
        let d = d.max(1);
        Divisor { d, m: (1u64 << Self::SHIFT).div_ceil(d as u64) }
    }
    /// `n / d`, by the multiply within its range (a division outside it).
    #[inline]
    fn div(self, n: i32) -> i32 {
        if (0..1 << 24).contains(&n) {
            ((n as u64 * self.m) >> Self::SHIFT) as i32
        } else {
            n / self.d
        }
    }
}

/// The fields of a [`Geometry`] as encoded (the same encoding), checked by
/// [`Geometry::new`] on decoding.
#[derive(Deserialize)]
struct GeometryFields {
    width: i32,
    height: i32,
    grid: i32,
}

impl TryFrom<GeometryFields> for Geometry {
    type Error = GeometryError;
    fn try_from(f: GeometryFields) -> Result<Self, GeometryError> {
        Geometry::new(f.width, f.height, f.grid)
    }
}

/// Why a geometry is not usable.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum GeometryError {
    #[error("arena width and height must be positive and even, got {width}x{height}")]
    BadArena { width: i32, height: i32 },
    #[error("arena {field} {value} exceeds {max}")]
    TooLarge { field: &'static str, value: i32, max: i32 },
    #[error("grid size {grid} must be positive and divide half the arena ({half_w} and {half_h})")]
    BadGrid { grid: i32, half_w: i32, half_h: i32 },
    #[error("grid size {grid} makes {cells} cells, more than {max}")]
    TooManyCells { grid: i32, cells: u64, max: u64 },
}

impl GeometryError {
    /// The key at fault: `width`, `height` or `grid`.
    pub fn field(&self) -> &'static str {
        match self {
            GeometryError::BadArena { width, .. } if *width > 0 && width % 2 == 0 => "height",
            GeometryError::BadArena { .. } => "width",
            GeometryError::TooLarge { field, .. } => field,
            GeometryError::BadGrid { .. } | GeometryError::TooManyCells { .. } => "grid",
        }
    }
}

impl Geometry {
    pub fn new(width: i32, height: i32, grid: i32) -> Result<Self, GeometryError> {
        if width <= 0 || height <= 0 || width % 2 != 0 || height % 2 != 0 {
            return Err(GeometryError::BadArena { width, height });
        }
        for (field, value) in [("width", width), ("height", height)] {
            if value > MAX_ARENA_SIDE {
                return Err(GeometryError::TooLarge { field, value, max: MAX_ARENA_SIDE });
            }
        }
        let (half_w, half_h) = (width / 2, height / 2);
        if grid <= 0 || half_w % grid != 0 || half_h % grid != 0 {
            return Err(GeometryError::BadGrid { grid, half_w, half_h });
        }
        let cells = (width / grid) as u64 * (height / grid) as u64;
        if cells > MAX_CELLS {
            return Err(GeometryError::TooManyCells { grid, cells, max: MAX_CELLS });
        }
        Ok(Geometry::derived(width, height, grid))
    }

    /// The geometry with its derived fields, unchecked.
    fn derived(width: i32, height: i32, grid: i32) -> Geometry {
        Geometry {
            width,
            height,
            grid,
            cols: Divisor::new(width / grid),
            rows: height / grid,
            by_grid: Divisor::new(grid),
        }
    }

    /// Arena width.
    #[inline]
    pub fn width(&self) -> i32 {
        self.width
    }
    /// Arena height.
    #[inline]
    pub fn height(&self) -> i32 {
        self.height
    }
    /// Grid size (side of a cell).
    #[inline]
    pub fn grid(&self) -> i32 {
        self.grid
    }
    #[inline]
    pub fn half_w(&self) -> i32 {
        self.width / 2
    }
    #[inline]
    pub fn half_h(&self) -> i32 {
        self.height / 2
    }
    /// Number of columns (cells along x).
    #[inline]
    pub fn cols(&self) -> i32 {
        self.cols.d
    }
    /// Number of rows (cells along y).
    #[inline]
    pub fn rows(&self) -> i32 {
        self.rows
    }
    /// Number of cells (widened: the product is computed in `usize`).
    #[inline]
    pub fn cell_count(&self) -> usize {
        self.cols() as usize * self.rows() as usize
    }

    /// Column/row of a point: floor division, points at or beyond the +edge go to the
    /// last column/row, points beyond the −edge to the first (REFERENCE §1.2).
    ///
    /// Half the arena is a multiple of the grid, so the column of x is
    /// ⌊(x + W/2) / GS⌋, clamped: one division per axis in the usual case (this runs
    /// for every agent and object look-up of every step).
    #[inline]
    pub fn col_row(&self, p: Pos) -> (i32, i32) {
        let along = |v: i32, extent: i32, last: i32| {
            let t = i64::from(v) + i64::from(extent / 2);
            if t <= 0 {
                0
            } else if t >= i64::from(extent) {
                last
            } else {
                self.by_grid.div(t as i32)
            }
        };
        (along(p.x, self.width, self.cols.d - 1), along(p.y, self.height, self.rows - 1))
    }

    #[inline]
    pub fn cell_of(&self, p: Pos) -> CellIdx {
        let (c, r) = self.col_row(p);
        (r * self.cols() + c) as CellIdx
    }

    /// Column and row of a cell index.
    #[inline]
    pub fn cell_col_row(&self, cell: CellIdx) -> (i32, i32) {
        let c = cell as i32;
        let r = self.cols.div(c);
        (c - r * self.cols.d, r)
    }

    /// The lower-left corner of a cell, in arena coordinates.
    pub fn cell_origin(&self, cell: CellIdx) -> Pos {
        let (c, r) = self.cell_col_row(cell);
        Pos::new(c * self.grid - self.half_w(), r * self.grid - self.half_h())
    }

    /// Neighbourhood N(p, r): the cell of p when r ≤ GS, otherwise the square block of
    /// cells within ⌊r/GS⌋ columns and rows, clipped at the arena edge. Calls `f` for each
    /// cell in row-major order.
    pub fn for_each_neighbourhood_cell(&self, p: Pos, radius: i32, mut f: impl FnMut(CellIdx)) {
        self.any_neighbourhood_cell(p, radius, |c| {
            f(c);
            false
        });
    }

    /// Does `f` hold for a cell of N(p, r)? Tries the cells in row-major order and stops
    /// at the first that does.
    pub fn any_neighbourhood_cell(&self, p: Pos, radius: i32, mut f: impl FnMut(CellIdx) -> bool) -> bool {
        let (c0, r0) = self.col_row(p);
        let s = self.reach(radius);
        for r in (r0 - s).max(0)..=r0.saturating_add(s).min(self.rows() - 1) {
            for c in (c0 - s).max(0)..=c0.saturating_add(s).min(self.cols() - 1) {
                if f((r * self.cols() + c) as CellIdx) {
                    return true;
                }
            }
        }
        false
    }

    /// How many columns and rows beyond its own cell an object of `radius` is registered
    /// in: 0 when r ≤ GS, otherwise ⌊r/GS⌋ (REFERENCE §1.2).
    pub fn reach(&self, radius: i32) -> i32 {
        if radius <= self.grid {
            0
        } else {
            radius / self.grid
        }
    }

    /// Is an object at `p` of `radius` registered in `cell` (does N(p, r) hold it)?
    pub fn registered_in(&self, p: Pos, radius: i32, cell: CellIdx) -> bool {
        let (c, r) = self.cell_col_row(cell);
        let (oc, or) = self.col_row(p);
        let s = self.reach(radius);
        (c - oc).abs() <= s && (r - or).abs() <= s
    }

    /// The cells of N(p, r) as a vector (row-major).
    pub fn neighbourhood(&self, p: Pos, radius: i32) -> Vec<CellIdx> {
        let mut v = Vec::new();
        self.for_each_neighbourhood_cell(p, radius, |c| v.push(c));
        v
    }

    /// Axis-aligned box (x1, y1, x2, y2) covered by the cells of N(p, r), as used by the
    /// obstacle-avoidance ray test (REFERENCE §2.4).
    pub fn neighbourhood_box(&self, p: Pos, radius: i32) -> (i32, i32, i32, i32) {
        let (c0, r0) = self.col_row(p);
        let s = self.reach(radius);
        let (cl, ch) = ((c0 - s).max(0), c0.saturating_add(s).min(self.cols() - 1));
        let (rl, rh) = ((r0 - s).max(0), r0.saturating_add(s).min(self.rows() - 1));
        let g = self.grid;
        (cl * g - self.half_w(), rl * g - self.half_h(), (ch + 1) * g - self.half_w(), (rh + 1) * g - self.half_h())
    }

    /// Border rule of REFERENCE §1.1 applied to a proposed position: an overshooting axis
    /// is put 2 units inside the edge and the heading turns by π (per axis).
    pub fn reflect(&self, p: Pos, heading: f64) -> (Pos, f64) {
        let (mut x, mut y, mut h) = (p.x, p.y, heading);
        let (hw, hh) = (self.half_w(), self.half_h());
        if x > hw {
            x = hw - 2;
            h += std::f64::consts::PI;
        } else if x < -hw {
            x = -hw + 2;
            h += std::f64::consts::PI;
        }
        if y > hh {
            y = hh - 2;
            h += std::f64::consts::PI;
        } else if y < -hh {
            y = -hh + 2;
            h += std::f64::consts::PI;
        }
        (Pos::new(x, y), h.rem_euclid(std::f64::consts::TAU))
    }

    /// Does this position lie inside the (closed) arena?
    pub fn contains(&self, p: Pos) -> bool {
        p.x.abs() <= self.half_w() && p.y.abs() <= self.half_h()
    }
}

/// Round half to even, as NumPy's `round` does.
pub fn round_half_even(v: f64) -> i32 {
    let r = v.round();
    if (v - v.trunc()).abs() == 0.5 {
        (2.0 * (v / 2.0).round()) as i32
    } else {
        r as i32
    }
}

/// The `Move` primitive's destination (REFERENCE §1.6 steps 1–3): step length `speed`
/// along `heading`, rounded half-to-even, then the border rule.
pub fn step_destination(geom: &Geometry, from: Pos, heading: f64, speed: f64) -> (Pos, f64) {
    let x = round_half_even(from.x as f64 + speed * heading.cos());
    let y = round_half_even(from.y as f64 + speed * heading.sin());
    geom.reflect(Pos::new(x, y), heading)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The reference's rule, literally: floor division, then the edges.
    fn col_row_literal(g: &Geometry, p: Pos) -> (i32, i32) {
        let gs = g.grid;
        let kx = if p.x >= g.half_w() { g.half_w() / gs - 1 } else { p.x.div_euclid(gs) };
        let ky = if p.y >= g.half_h() { g.half_h() / gs - 1 } else { p.y.div_euclid(gs) };
        ((kx + g.half_w() / gs).clamp(0, g.cols() - 1), (ky + g.half_h() / gs).clamp(0, g.rows() - 1))
    }

    #[test]
    fn col_row_is_the_literal_rule() {
        for (w, h, gs) in [(100, 100, 10), (100, 100, 2), (100, 100, 5), (60, 40, 10), (2, 2, 1), (100, 100, 50)] {
            let g = Geometry::new(w, h, gs).unwrap();
            for x in -w..=w {
                for y in [-h - 3, -h / 2 - 1, -h / 2, -1, 0, 1, h / 2 - 1, h / 2, h + 7] {
                    for p in [Pos::new(x, y), Pos::new(y, x)] {
                        assert_eq!(g.col_row(p), col_row_literal(&g, p), "{w}x{h}/{gs} at {p:?}");
                    }
                }
            }
            for p in [Pos::new(i32::MAX, i32::MIN), Pos::new(i32::MIN, i32::MAX)] {
                assert_eq!(g.col_row(p), col_row_literal(&g, p));
            }
        }
    }

    #[test]
    fn cell_rules_match_reference() {
        let g = Geometry::new(100, 100, 10).unwrap();
        // The origin belongs to the cell [0,10)x[0,10): column 5, row 5.
        assert_eq!(g.col_row(Pos::new(0, 0)), (5, 5));
        assert_eq!(g.cell_of(Pos::new(0, 0)), 55);
        assert_eq!(g.col_row(Pos::new(-1, -1)), (4, 4));
        assert_eq!(g.col_row(Pos::new(-30, -30)), (2, 2));
        assert_eq!(g.col_row(Pos::new(50, 50)), (9, 9));
        assert_eq!(g.col_row(Pos::new(-50, -50)), (0, 0));
        assert_eq!(g.col_row(Pos::new(9, 10)), (5, 6));
        assert_eq!(g.cell_count(), 100);
    }

    #[test]
    fn neighbourhoods() {
        let g = Geometry::new(100, 100, 10).unwrap();
        assert_eq!(g.neighbourhood(Pos::new(0, 0), 10), vec![55]);
        let g5 = Geometry::new(100, 100, 5).unwrap();
        assert_eq!(g5.neighbourhood(Pos::new(0, 0), 10).len(), 25);
        let g2 = Geometry::new(100, 100, 2).unwrap();
        assert_eq!(g2.neighbourhood(Pos::new(0, 0), 10).len(), 121);
        assert_eq!(g2.neighbourhood(Pos::new(0, 0), 3).len(), 9);
        // Clipped at the edge.
        assert_eq!(g2.neighbourhood(Pos::new(-50, -50), 3).len(), 4);
        assert_eq!(g.neighbourhood_box(Pos::new(30, 30), 10), (30, 30, 40, 40));
    }

    #[test]
    fn border_rule() {
        let g = Geometry::new(100, 100, 10).unwrap();
        let (p, h) = g.reflect(Pos::new(51, 0), 0.0);
        assert_eq!(p, Pos::new(48, 0));
        assert!((h - std::f64::consts::PI).abs() < 1e-12);
        let (p, h) = g.reflect(Pos::new(51, -52), 0.5);
        assert_eq!(p, Pos::new(48, -48));
        assert!((h - 0.5).abs() < 1e-12);
        assert_eq!(g.reflect(Pos::new(50, 50), 1.0).0, Pos::new(50, 50));
    }

    #[test]
    fn bankers_rounding() {
        assert_eq!(round_half_even(0.5), 0);
        assert_eq!(round_half_even(1.5), 2);
        assert_eq!(round_half_even(2.5), 2);
        assert_eq!(round_half_even(-0.5), 0);
        assert_eq!(round_half_even(-1.5), -2);
        assert_eq!(round_half_even(1.4), 1);
        assert_eq!(round_half_even(-1.6), -2);
    }

    #[test]
    fn bad_geometry_is_an_error() {
        assert!(Geometry::new(100, 100, 7).is_err());
        assert!(Geometry::new(0, 100, 10).is_err());
        assert_eq!(Geometry::new(100, 101, 10).unwrap_err().field(), "height");
        assert_eq!(Geometry::new(-2, 100, 10).unwrap_err().field(), "width");
        assert_eq!(Geometry::new(100, 100, 7).unwrap_err().field(), "grid");
    }

    #[test]
    fn arena_size_and_cell_count_are_bounded() {
        // At the limits.
        let g = Geometry::new(MAX_ARENA_SIDE, MAX_ARENA_SIDE, 10).unwrap();
        assert_eq!(g.cell_count() as u64, MAX_CELLS);
        assert!(Geometry::new(MAX_ARENA_SIDE, 100, 1).is_ok());
        // Above them, naming the key.
        let e = Geometry::new(MAX_ARENA_SIDE + 2, 100, 1).unwrap_err();
        assert_eq!((e.field(), e.to_string()), ("width", "arena width 10002 exceeds 10000".to_string()));
        assert_eq!(Geometry::new(100, i32::MAX - 1, 1).unwrap_err().field(), "height");
        let e = Geometry::new(MAX_ARENA_SIDE, MAX_ARENA_SIDE, 5).unwrap_err();
        assert_eq!(e.field(), "grid");
        assert!(e.to_string().contains("4000000 cells"), "{e}");
    }

    /// The multiply-and-shift division equals `/` at every multiple of every divisor a
    /// geometry can have and one below it, for every coordinate and cell index a
    /// geometry can have (and beyond that range, where it divides).
    #[test]
    fn divisors_divide_exactly() {
        for d in 1..=MAX_ARENA_SIDE {
            let v = Divisor::new(d);
            let mut n = 0i64;
            while n <= MAX_CELLS as i64 + 1 {
                for k in [n - 1, n, n + 1] {
                    if k >= 0 {
                        assert_eq!(v.div(k as i32), k as i32 / d, "{k} / {d}");
                    }
                }
                n += i64::from(d);
            }
            for k in [-1, -d, 1 << 24, i32::MAX] {
                assert_eq!(v.div(k), k / d, "{k} / {d}");
            }
        }
    }

    #[test]
    fn cell_count_is_widened_and_cells_fit() {
        // An unchecked geometry (public fields) whose cell count overflows i32.
        let g = Geometry::derived(100_000, 100_000, 1);
        assert_eq!(g.cell_count(), 10_000_000_000);
        let g = Geometry::new(MAX_ARENA_SIDE, 100, 1).unwrap();
        let corner = Pos::new(MAX_ARENA_SIDE / 2, 50);
        assert_eq!(g.cell_of(corner) as usize, g.cell_count() - 1);
    }

    #[test]
    fn huge_radii_are_clipped_not_overflowed() {
        let g = Geometry::new(100, 100, 1).unwrap();
        let mut n = 0;
        g.for_each_neighbourhood_cell(Pos::new(49, 49), i32::MAX, |_| n += 1);
        assert_eq!(n, g.cell_count());
        assert_eq!(g.neighbourhood_box(Pos::new(49, 49), i32::MAX), (-50, -50, 50, 50));
        let mut seen = 0;
        assert!(g.any_neighbourhood_cell(Pos::new(0, 0), 5, |c| {
            seen += 1;
            c == g.cell_of(Pos::new(0, 0))
        }));
        assert!(seen < 121, "stops at the first hit");
    }

    #[test]
    fn registration_rule() {
        let g = Geometry::new(100, 100, 10).unwrap();
        for radius in [3, 10, 11, 25] {
            let cells = g.neighbourhood(Pos::new(12, -31), radius);
            for cell in 0..g.cell_count() as CellIdx {
                assert_eq!(g.registered_in(Pos::new(12, -31), radius, cell), cells.contains(&cell), "{radius} {cell}");
            }
        }
    }

    #[test]
    fn decoding_checks_the_geometry() {
        let g = Geometry::new(100, 60, 10).unwrap();
        let bytes = postcard::to_stdvec(&g).unwrap();
        assert_eq!(postcard::from_bytes::<Geometry>(&bytes), Ok(g));
        // Same encoding as three plain i32 fields.
        assert_eq!(bytes, postcard::to_stdvec(&(100i32, 60i32, 10i32)).unwrap());
        for bad in [(100i32, 60i32, 7i32), (i32::MAX - 1, 2, 1), (0, 0, 0)] {
            let bytes = postcard::to_stdvec(&bad).unwrap();
            assert!(postcard::from_bytes::<Geometry>(&bytes).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn decoding_checks_the_geometry_and_keeps_the_wire_format() {
        let g = Geometry::new(100, 60, 10).unwrap();
        let bytes = crate::encode(&g).unwrap();
        assert_eq!(crate::decode::<Geometry>(&bytes).unwrap(), g);
        assert_eq!(crate::encode(&(100i32, 60i32, 10i32)).unwrap(), bytes);
        for (w, h, gs) in [(100, 60, 0), (100, 60, 7), (0, 60, 10), (-100, 60, 10)] {
            let bad = crate::encode(&(w, h, gs)).unwrap();
            assert!(crate::decode::<Geometry>(&bad).is_err(), "{w}x{h}, grid {gs}");
        }
    }
}
