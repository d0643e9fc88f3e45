//! Limits on everything that crosses a trust boundary (issue 17): control commands,
//! configuration sizes, agent-id ranges. Written once here; the world server, the
//! `geese control` command and the configuration checks all use them.
//!
//! The limits are far above every setting of the reference runs (100 × 100 arena, GS 10,
//! 100 agents, 12,000 steps, 1–5 obstacles of radius 5 or 10) and low enough that no
//! accepted value overflows the `i32` arithmetic of [`Geometry`], makes a loop run for
//! billions of iterations or allocates more than about a gigabyte.
use crate::geometry::Geometry;
use crate::message::{Control, Perturbation};

/// Largest arena width or height (units). With [`MAX_CELLS`] it keeps every cell index
/// and coordinate product of [`Geometry`] far inside `i32`.
pub const MAX_ARENA_SIDE: i32 = 10_000;
/// Most grid cells an arena may have (`(W / GS) × (H / GS)`): the world keeps two lists
/// per cell and every learner one bit per cell.
pub const MAX_CELLS: u64 = 1_000_000;
/// Most agents of a run.
pub const MAX_AGENTS: u32 = 1_000_000;
/// Most food or debris units of a world.
pub const MAX_ITEMS: u32 = 1_000_000;
/// Most steps of a run (833 times the reference's 12,000). A scheduled change for a
/// later step could never apply.
pub const MAX_STEPS: u64 = 10_000_000;
/// Most obstacles one [`Perturbation::AddObstacles`] may add.
pub const MAX_ADD_OBSTACLES: u32 = 1_000;
/// Most perturbations a run configuration may schedule.
pub const MAX_SCHEDULED: usize = 10_000;

/// Largest obstacle radius in an arena: its width or height, whichever is larger (an
/// obstacle that large already covers every cell).
pub fn max_radius(geom: &Geometry) -> i32 {
    geom.width().max(geom.height())
}

/// A control command or value outside its limits. The message names the field and the
/// value, e.g. `AddObstacles.count 4294967295 exceeds 1000`.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{field} {value} {rule}")]
pub struct InvalidCommand {
    /// The field, as `Variant.field` (`AddObstacles.radius`, `SetIp`, `Schedule.at_step`).
    pub field: &'static str,
    /// The value received, as text (`NaN` for a NaN).
    pub value: String,
    /// What it breaks (`exceeds 1000`, `is not in [0, 1]`).
    pub rule: String,
}

impl InvalidCommand {
    fn new(field: &'static str, value: impl std::fmt::Display, rule: impl Into<String>) -> Self {
        InvalidCommand { field, value: value.to_string(), rule: rule.into() }
    }
}

/// `value` must be a finite number in [0, 1] (probabilities, loss rates, fractions;
/// NaN and infinities fail).
pub fn check_unit(field: &'static str, value: f64) -> Result<(), InvalidCommand> {
    if (0.0..=1.0).contains(&value) {
        Ok(())
    } else {
        Err(InvalidCommand::new(field, value, "is not in [0, 1]"))
    }
}

/// A step-rate limit must be 0 (no limit) or a number of steps per second in
/// [[`crate::view::MIN_STEP_RATE`], [`crate::view::MAX_STEP_RATE`]]: a tiny positive
/// rate would make the wait between two steps longer than any clock holds (geese-fuzz
/// found a 1e-300 that panicked the world server).
pub fn check_step_rate(r: f64) -> Result<(), InvalidCommand> {
    use crate::view::{MAX_STEP_RATE, MIN_STEP_RATE};
    if r == 0.0 || (MIN_STEP_RATE..=MAX_STEP_RATE).contains(&r) {
        Ok(())
    } else {
        Err(InvalidCommand::new(
            "StepRate",
            r,
            format!("is neither 0 nor in [{MIN_STEP_RATE}, {MAX_STEP_RATE}] steps/s"),
        ))
    }
}

/// `value` must not exceed `max`.
pub fn check_max<T: PartialOrd + std::fmt::Display>(
    field: &'static str,
    value: T,
    max: T,
) -> Result<(), InvalidCommand> {
    if value <= max {
        Ok(())
    } else {
        Err(InvalidCommand::new(field, &value, format!("exceeds {max}")))
    }
}

impl Perturbation {
    /// Check the change against the limits, for a world of geometry `geom`:
    /// `AddObstacles.count` ≤ [`MAX_ADD_OBSTACLES`], `AddObstacles.radius` in
    /// [1, [`max_radius`]], IP, gene loss and kill fraction finite and in [0, 1].
    /// A count or fraction of 0 is allowed (it changes nothing).
    pub fn validate(&self, geom: &Geometry) -> Result<(), InvalidCommand> {
        match *self {
            Perturbation::AddObstacles { count, radius } => {
                check_max("AddObstacles.count", count, MAX_ADD_OBSTACLES)?;
                if radius < 1 {
                    return Err(InvalidCommand::new("AddObstacles.radius", radius, "is below 1"));
                }
                let max = max_radius(geom);
                if radius > max {
                    return Err(InvalidCommand::new(
                        "AddObstacles.radius",
                        radius,
                        format!("exceeds {max} (the arena is {}x{})", geom.width(), geom.height()),
                    ));
                }
                Ok(())
            }
            Perturbation::AddObstacleAt { x, y, radius } => {
                if radius < 1 {
                    return Err(InvalidCommand::new("AddObstacleAt.radius", radius, "is below 1"));
                }
                let max = max_radius(geom);
                if radius > max {
                    return Err(InvalidCommand::new("AddObstacleAt.radius", radius, format!("exceeds {max}")));
                }
                if !geom.contains(crate::Pos::new(x, y)) {
                    return Err(InvalidCommand::new(
                        "AddObstacleAt",
                        format!("({x}, {y})"),
                        format!("is outside the {}x{} arena", geom.width(), geom.height()),
                    ));
                }
                Ok(())
            }
            Perturbation::SetIp(ip) => check_unit("SetIp", ip),
            Perturbation::SetLateralTransfer(_) => Ok(()),
            Perturbation::SetGeneLoss(p) => check_unit("SetGeneLoss", p),
            Perturbation::KillFraction(f) => check_unit("KillFraction", f),
            // Either task is a world this arena can hold; whether it is the task
            // already running is the world's to say (it knows the schedule).
            Perturbation::SwitchTask(_) => Ok(()),
        }
    }
}

impl Control {
    /// Check a command received on the control plane against the limits, for a world of
    /// geometry `geom`: a scheduled change is checked by [`Perturbation::validate`] and
    /// its `at_step` must not exceed [`MAX_STEPS`]. `Start` and `Stop` are always valid.
    pub fn validate(&self, geom: &Geometry) -> Result<(), InvalidCommand> {
        match self {
            Control::Start | Control::Stop | Control::Pause | Control::Resume => Ok(()),
            Control::StepRate(r) => check_step_rate(*r),
            Control::Schedule { at_step, change } => {
                check_max("Schedule.at_step", *at_step, MAX_STEPS)?;
                change.validate(geom)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn arena() -> Geometry {
        Geometry::new(100, 60, 10).unwrap()
    }

    fn field(p: Perturbation) -> &'static str {
        p.validate(&arena()).unwrap_err().field
    }

    #[test]
    fn obstacle_counts_and_radii_are_bounded() {
        let g = arena();
        let add = |count, radius| Perturbation::AddObstacles { count, radius };
        assert_eq!(add(MAX_ADD_OBSTACLES, 10).validate(&g), Ok(()));
        assert_eq!(add(0, 10).validate(&g), Ok(()));
        assert_eq!(add(3, 100).validate(&g), Ok(()), "radius = the larger side");
        let e = add(u32::MAX, 10).validate(&g).unwrap_err();
        assert_eq!(e.to_string(), "AddObstacles.count 4294967295 exceeds 1000");
        assert_eq!(add(MAX_ADD_OBSTACLES + 1, 10).validate(&g).unwrap_err().field, "AddObstacles.count");
        let e = add(1, 101).validate(&g).unwrap_err();
        assert_eq!(e.to_string(), "AddObstacles.radius 101 exceeds 100 (the arena is 100x60)");
        for r in [0, -1, i32::MIN] {
            assert_eq!(field(add(1, r)), "AddObstacles.radius");
        }
        assert_eq!(field(add(1, i32::MAX)), "AddObstacles.radius");
    }

    #[test]
    fn rates_and_fractions_are_finite_and_in_the_unit_interval() {
        let g = arena();
        for ok in [0.0, 0.5, 1.0] {
            assert_eq!(Perturbation::SetIp(ok).validate(&g), Ok(()));
            assert_eq!(Perturbation::SetGeneLoss(ok).validate(&g), Ok(()));
            assert_eq!(Perturbation::KillFraction(ok).validate(&g), Ok(()));
        }
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, -0.01, 1.01] {
            assert_eq!(field(Perturbation::SetIp(bad)), "SetIp");
            assert_eq!(field(Perturbation::SetGeneLoss(bad)), "SetGeneLoss");
            assert_eq!(field(Perturbation::KillFraction(bad)), "KillFraction");
        }
        assert_eq!(Perturbation::SetIp(f64::NAN).validate(&g).unwrap_err().to_string(), "SetIp NaN is not in [0, 1]");
        assert_eq!(Perturbation::SetLateralTransfer(false).validate(&g), Ok(()));
    }

    #[test]
    fn control_commands() {
        let g = arena();
        assert_eq!(Control::Stop.validate(&g), Ok(()));
        assert_eq!(Control::Start.validate(&g), Ok(()));
        let at = |at_step, change| Control::Schedule { at_step, change };
        assert_eq!(at(MAX_STEPS, Perturbation::SetIp(0.5)).validate(&g), Ok(()));
        let e = at(MAX_STEPS + 1, Perturbation::SetIp(0.5)).validate(&g).unwrap_err();
        assert_eq!(e.to_string(), format!("Schedule.at_step {} exceeds {MAX_STEPS}", MAX_STEPS + 1));
        let e = at(5, Perturbation::AddObstacles { count: u32::MAX, radius: 10 }).validate(&g).unwrap_err();
        assert_eq!(e.field, "AddObstacles.count");
    }

    #[test]
    fn helpers() {
        assert_eq!(check_max("x", 5, 5), Ok(()));
        assert_eq!(check_max("x", 6, 5).unwrap_err().to_string(), "x 6 exceeds 5");
        assert!(check_unit("p", -0.0).is_ok());
        assert_eq!(max_radius(&arena()), 100);
    }
}
