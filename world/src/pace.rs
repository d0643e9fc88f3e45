//! The pace of a watched run, sans IO: pause, a step-rate limit, and the bound on how
//! often a frame goes to the live viewer. One [`Pace`] serves the world server and the
//! in-process run, so both honour the viewer's controls the same way.
use geese_proto::view::MAX_FRAMES_PER_SECOND;
use geese_proto::Control;
use std::time::{Duration, Instant};

#[derive(Debug, Clone)]
pub struct Pace {
    paused: bool,
    /// Steps per second at most; 0 = no limit.
    rate: f64,
    last_step: Option<Instant>,
    last_frame: Option<Instant>,
    /// A frame is owed whatever the rate bound (the pace changed: the viewer must see it).
    owed: bool,
}

impl Default for Pace {
    fn default() -> Self {
        Pace::new()
    }
}

impl Pace {
    pub fn new() -> Self {
        Pace { paused: false, rate: 0.0, last_step: None, last_frame: None, owed: false }
    }

    /// Take a pace command (`Pause`, `Resume`, `StepRate`, already validated); false for
    /// any other command, which the caller handles.
    pub fn on_control(&mut self, c: &Control) -> bool {
        match *c {
            Control::Pause => self.paused = true,
            Control::Resume => self.paused = false,
            // Checked again here: a rate outside the limits would overflow the clock.
            Control::StepRate(r) if geese_proto::limits::check_step_rate(r).is_ok() => self.rate = r,
            _ => return false,
        }
        self.owed = true;
        true
    }

    pub fn paused(&self) -> bool {
        self.paused
    }

    /// The step-rate limit (steps per second; 0 = none).
    pub fn rate(&self) -> f64 {
        self.rate
    }

    /// When the next step may begin: `None` while paused, `now` or later otherwise.
    pub fn step_at(&self, now: Instant) -> Option<Instant> {
        if self.paused {
            return None;
        }
        match self.last_step {
            Some(last) if self.rate > 0.0 => Some(now.max(last + Duration::from_secs_f64(1.0 / self.rate))),
            _ => Some(now),
        }
    }

    /// A step begins at `now`.
    pub fn stepped(&mut self, now: Instant) {
        self.last_step = Some(now);
    }

    /// Is a frame due at `now` (at most [`MAX_FRAMES_PER_SECOND`], or one is owed)? If so,
    /// it counts as sent.
    pub fn frame_due(&mut self, now: Instant) -> bool {
        let gap = Duration::from_secs_f64(1.0 / MAX_FRAMES_PER_SECOND);
        let due = self.owed || self.last_frame.is_none_or(|t| now >= t + gap);
        if due {
            self.last_frame = Some(now);
            self.owed = false;
        }
        due
    }

    /// Owe the viewer a frame (one just arrived and must see the current step).
    pub fn owe_frame(&mut self) {
        self.owed = true;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pause_holds_resume_releases_and_the_rate_spaces_steps() {
        let t0 = Instant::now();
        let mut p = Pace::new();
        assert_eq!(p.step_at(t0), Some(t0));
        p.stepped(t0);
        assert_eq!(p.step_at(t0), Some(t0), "no limit: at once");
        assert!(p.on_control(&Control::StepRate(4.0)));
        assert_eq!(p.step_at(t0), Some(t0 + Duration::from_millis(250)));
        assert_eq!(p.step_at(t0 + Duration::from_secs(1)), Some(t0 + Duration::from_secs(1)));
        assert!(p.on_control(&Control::Pause));
        assert_eq!(p.step_at(t0 + Duration::from_secs(9)), None);
        assert!(p.on_control(&Control::Resume));
        assert!(p.step_at(t0).is_some());
        assert!(!p.on_control(&Control::Stop), "not a pace command");
        assert!(!p.on_control(&Control::StepRate(1e-300)), "refused: no clock holds 1e300 s");
        assert_eq!(p.rate(), 4.0);
    }

    #[test]
    fn frames_are_bounded_in_rate_but_a_pace_change_is_shown_at_once() {
        let t0 = Instant::now();
        let mut p = Pace::new();
        assert!(p.frame_due(t0));
        assert!(!p.frame_due(t0 + Duration::from_millis(10)));
        let gap = Duration::from_secs_f64(1.0 / MAX_FRAMES_PER_SECOND);
        assert!(p.frame_due(t0 + gap));
        p.on_control(&Control::Pause);
        assert!(p.frame_due(t0 + gap), "owed after a pause");
        assert!(!p.frame_due(t0 + gap));
    }
}
