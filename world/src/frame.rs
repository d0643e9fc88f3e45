//! The live viewer's picture of a world: built here once for the in-process run and the
//! world server alike.
use crate::pace::Pace;
use crate::World;
use geese_proto::view::{AgentMark, ObjectMark, ViewFrame};
use geese_proto::StepReport;

/// The frame of `w` after the step `rep` reports, in a run of `steps` steps.
pub fn frame(w: &World, rep: &StepReport, steps: u64, pace: &Pace) -> ViewFrame {
    let g = w.geometry();
    let objects = w.objects().collect::<Vec<_>>();
    let agents = w
        .bodies()
        .iter()
        .map(|b| AgentMark {
            id: b.id,
            x: b.pos.x,
            y: b.pos.y,
            heading: b.heading as f32,
            live: b.live,
            class: b.class,
            carrying: b.carrying.iter().filter_map(|&o| objects.get(o as usize)).map(|o| o.info.kind).collect(),
        })
        .collect();
    ViewFrame {
        step: rep.step,
        steps,
        task_pct: rep.task_pct,
        lt_mean: rep.lt_mean,
        live_agents: rep.live_agents,
        width: g.width(),
        height: g.height(),
        grid: g.grid(),
        paused: pace.paused(),
        step_rate: pace.rate(),
        agents,
        objects: objects
            .iter()
            .filter(|o| o.registered)
            .map(|o| ObjectMark { kind: o.info.kind, x: o.info.pos.x, y: o.info.pos.y, radius: o.info.radius })
            .collect(),
        events: w.events().to_vec(),
    }
}
