//! Where each rung of the solver ladder holds, and what a scene does when a frame leaves it.
//!
//! A rung's limits are read from the study's table ([`SolverTable`], the same measurements that
//! `solver = "auto"` chooses by), at the scene's relative force `tolerance`:
//! - contact radius over gel thickness a/h: the largest studied a/h up to which every studied
//!   a/h meets the tolerance on the study's finest grid (the model's error, not the grid's: the
//!   half-space rung ignores the layer, so it stops at thin contacts on thick gels; points where
//!   a rung declined the case are the rung's own refusals and set no limit here);
//! - indentation depth over gel thickness δ/h: the deepest swept depth up to which every swept
//!   depth meets the tolerance against finite-strain finite elements, at the scene's friction
//!   coefficient ([`SolverTable::depth_error`]: friction at depth is where the rungs part); a
//!   frame loaded tangentially (sliding) is held to the press-and-slide rows as well, which
//!   grade the tangential force after a slide.
//!
//! A rung that meets the tolerance at no studied point (the geometric rung makes no force claim)
//! is outside its validity whenever it is in contact. The mechanics grid's resolution is not a
//! validity limit: `solver = "auto"` and `mechanics_stride` choose it.

use serde::Deserialize;

use crate::SolverKind;
use crate::auto::SolverTable;

/// What a scene does with a frame outside its rung's validity (`validity = "..."`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ValidityPolicy {
    /// Stop with an error naming the frame.
    Error,
    /// Record it in the frame's labels and count it in the run's summary.
    #[default]
    Warn,
    /// Under `solver = "auto"`: solve the frame, and the rest of the trajectory, on the next rung
    /// up that holds there.
    Escalate,
}

impl ValidityPolicy {
    /// The name used in scene files.
    pub fn name(self) -> &'static str {
        match self {
            ValidityPolicy::Error => "error",
            ValidityPolicy::Warn => "warn",
            ValidityPolicy::Escalate => "escalate",
        }
    }
}

/// Which limit a frame passed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Limit {
    /// Contact radius over gel thickness.
    ContactRadiusOverThickness,
    /// Indentation depth over gel thickness.
    DepthOverThickness,
    /// Indentation depth over gel thickness of a frame loaded tangentially.
    SlidingDepthOverThickness,
    /// The rung meets the tolerance nowhere in the study.
    Rung,
}

impl Limit {
    /// The name used in labels.
    pub fn name(self) -> &'static str {
        match self {
            Limit::ContactRadiusOverThickness => "a_over_h",
            Limit::DepthOverThickness => "depth_over_h",
            Limit::SlidingDepthOverThickness => "sliding_depth_over_h",
            Limit::Rung => "rung",
        }
    }
}

/// Whether a frame lies where its rung holds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Validity {
    /// Within every limit.
    Ok,
    /// Past `limit`: the frame's `value` against the rung's `bound` (for [`Limit::Rung`], the
    /// rung's smallest studied error against the tolerance).
    Outside {
        /// The limit passed.
        limit: Limit,
        /// The frame's value.
        value: f64,
        /// The rung's bound at the tolerance.
        bound: f64,
    },
}

impl Validity {
    /// `ok`, or the name of the limit passed.
    pub fn name(self) -> &'static str {
        match self {
            Validity::Ok => "ok",
            Validity::Outside { limit, .. } => limit.name(),
        }
    }

    /// True within every limit.
    pub fn is_ok(self) -> bool {
        self == Validity::Ok
    }
}

impl std::fmt::Display for Validity {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            Validity::Ok => f.write_str("within its validity"),
            Validity::Outside {
                limit: Limit::Rung,
                value,
                ..
            } => write!(
                f,
                "its force error is above the tolerance in every studied case (best {:.1} %)",
                100.0 * value
            ),
            Validity::Outside {
                limit: Limit::ContactRadiusOverThickness,
                value,
                bound,
            } => write!(
                f,
                "contact radius over gel thickness {value:.3} is past the rung's {bound:.3}"
            ),
            Validity::Outside {
                limit: Limit::DepthOverThickness,
                value,
                bound,
            } => write!(
                f,
                "indentation depth over gel thickness {value:.3} is past the rung's {bound:.3}"
            ),
            Validity::Outside {
                limit: Limit::SlidingDepthOverThickness,
                value,
                bound,
            } => write!(
                f,
                "indentation depth over gel thickness {value:.3} is past the rung's {bound:.3} \
                 for a sliding contact"
            ),
        }
    }
}

/// Where a rung holds at a tolerance, from the study's table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RungLimits {
    /// The rung.
    pub rung: SolverKind,
    /// Relative force tolerance the limits are for.
    pub tolerance: f64,
    /// Friction coefficient the depth limit is for.
    pub friction: f64,
    /// Largest contact radius over gel thickness where it holds; `None` if it holds at no
    /// studied point.
    pub max_a_over_h: Option<f64>,
    /// Largest indentation depth over gel thickness where it holds (∞ when the table has no
    /// depth sweep of the rung).
    pub max_depth_over_h: f64,
    /// The same for a contact loaded tangentially (the press-and-slide rows count too).
    pub max_sliding_depth_over_h: f64,
    /// The rung's smallest studied error on the finest grid (what [`Limit::Rung`] reports).
    pub best_rel_error: f64,
}

impl RungLimits {
    /// The limits of `rung` at `tolerance` with friction coefficient `friction` in `table`.
    pub fn of(table: &SolverTable, rung: SolverKind, tolerance: f64, friction: f64) -> RungLimits {
        let shallow = || {
            table
                .rows
                .iter()
                .filter(move |r| r.rung == rung && r.depth_over_h == 0.0)
        };
        let finest = shallow().map(|r| r.a_over_cell).reduce(f64::max);
        let mut at_finest: Vec<(f64, f64)> = shallow()
            .filter(|r| Some(r.a_over_cell) == finest && r.rel_error.is_finite())
            .map(|r| (r.a_over_h, r.rel_error))
            .collect();
        at_finest.sort_by(|a, b| a.0.total_cmp(&b.0));
        let max_a_over_h = at_finest
            .iter()
            .take_while(|(_, e)| *e <= tolerance)
            .map(|&(a, _)| a)
            .last();
        let best_rel_error = at_finest
            .iter()
            .map(|&(_, e)| e)
            .fold(f64::INFINITY, f64::min);
        let mut depths: Vec<f64> = table
            .rows
            .iter()
            .filter(|r| r.rung == rung && r.depth_over_h > 0.0)
            .map(|r| r.depth_over_h)
            .collect();
        depths.sort_by(f64::total_cmp);
        depths.dedup();
        let max_depth = |sliding: bool| match depths.first() {
            None => f64::INFINITY,
            Some(&shallowest) => depths
                .iter()
                .copied()
                .take_while(|&d| table.depth_error(rung, d, friction, sliding) <= tolerance)
                .last()
                .unwrap_or(shallowest),
        };
        RungLimits {
            rung,
            tolerance,
            friction,
            max_a_over_h,
            max_depth_over_h: max_depth(false),
            max_sliding_depth_over_h: max_depth(true),
            best_rel_error,
        }
    }

    /// Whether a frame with contact radius over gel thickness `a_over_h` and indentation depth
    /// over gel thickness `depth_over_h`, `sliding` (loaded tangentially) or not, lies within the
    /// limits (a frame out of contact does).
    pub fn check(
        &self,
        in_contact: bool,
        a_over_h: f64,
        depth_over_h: f64,
        sliding: bool,
    ) -> Validity {
        if !in_contact {
            return Validity::Ok;
        }
        let Some(max_a_over_h) = self.max_a_over_h else {
            return Validity::Outside {
                limit: Limit::Rung,
                value: self.best_rel_error,
                bound: self.tolerance,
            };
        };
        if depth_over_h > self.max_depth_over_h {
            return Validity::Outside {
                limit: Limit::DepthOverThickness,
                value: depth_over_h,
                bound: self.max_depth_over_h,
            };
        }
        if sliding && depth_over_h > self.max_sliding_depth_over_h {
            return Validity::Outside {
                limit: Limit::SlidingDepthOverThickness,
                value: depth_over_h,
                bound: self.max_sliding_depth_over_h,
            };
        }
        if a_over_h > max_a_over_h {
            return Validity::Outside {
                limit: Limit::ContactRadiusOverThickness,
                value: a_over_h,
                bound: max_a_over_h,
            };
        }
        Validity::Ok
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::auto::TableRow;

    fn row(rung: SolverKind, a_over_cell: f64, a_over_h: f64, depth: f64, e: f64) -> TableRow {
        TableRow {
            rung,
            a_over_cell,
            a_over_h,
            depth_over_h: depth,
            friction: 0.0,
            slide_over_a: 0.0,
            rel_error: e,
            ms_per_frame: 1.0,
        }
    }

    /// The limits are read on the finest grid, stop at the first studied point that misses
    /// (even if a later one meets again), ignore the rung's refusals, and depth follows the
    /// sweep's hard-side rule (the worst error up to the query); a slide's row bounds only
    /// sliding frames.
    #[test]
    fn limits_follow_the_table() {
        use SolverKind::Halfspace as H;
        let table = SolverTable {
            rows: vec![
                row(H, 5.0, 0.01, 0.0, 0.5), // coarse grid: not read
                row(H, 40.0, 0.005, 0.0, f64::INFINITY),
                row(H, 40.0, 0.01, 0.0, 0.01),
                row(H, 40.0, 0.1, 0.0, 0.015),
                row(H, 40.0, 0.5, 0.0, 0.03),
                row(H, 40.0, 1.0, 0.0, 0.01),
                row(H, 4.0, 0.2, 0.01, 0.015),
                row(H, 8.0, 0.4, 0.1, 0.01),
                row(H, 12.0, 0.6, 0.3, 0.019),
                row(H, 16.0, 0.8, 0.5, 0.025),
                TableRow {
                    slide_over_a: 0.5,
                    ..row(H, 8.0, 0.4, 0.1, 0.03)
                },
            ],
        };
        let limits = RungLimits::of(&table, H, 0.02, 0.0);
        assert_eq!(limits.max_a_over_h, Some(0.1));
        assert_eq!(limits.max_depth_over_h, 0.3);
        assert_eq!(limits.max_sliding_depth_over_h, 0.01);
        assert_eq!(limits.best_rel_error, 0.01);
        assert!(limits.check(true, 0.1, 0.3, false).is_ok());
        assert!(limits.check(false, 5.0, 5.0, true).is_ok());
        assert!(limits.check(true, 0.1, 0.01, true).is_ok());
        assert_eq!(
            limits.check(true, 0.1, 0.05, true),
            Validity::Outside {
                limit: Limit::SlidingDepthOverThickness,
                value: 0.05,
                bound: 0.01
            }
        );
        assert_eq!(
            limits.check(true, 0.2, 0.3, false),
            Validity::Outside {
                limit: Limit::ContactRadiusOverThickness,
                value: 0.2,
                bound: 0.1
            }
        );
        assert_eq!(limits.check(true, 0.2, 0.31, true).name(), "depth_over_h");
        let loose = RungLimits::of(&table, H, 0.04, 0.0);
        assert_eq!(loose.max_a_over_h, Some(1.0));
        assert_eq!(loose.max_depth_over_h, 0.5);
        assert_eq!(loose.max_sliding_depth_over_h, 0.5);
        let strict = RungLimits::of(&table, H, 0.001, 0.0);
        assert_eq!(strict.max_a_over_h, None);
        assert_eq!(strict.check(true, 0.0, 0.0, false).name(), "rung");
        assert!(strict.check(false, 0.0, 0.0, false).is_ok());
    }
}
