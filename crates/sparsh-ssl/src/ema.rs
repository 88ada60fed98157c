//! Exponential moving average of one module's weights into another of the same structure
//! (DINO teacher, JEPA target encoder).

use std::collections::VecDeque;

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::prelude::*;

struct Collect(VecDeque<Tensor<1>>);

impl ModuleVisitor for Collect {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let t = param.val().detach();
        let n = t.shape().num_elements();
        self.0.push_back(t.reshape([n]));
    }
}

struct Blend {
    source: VecDeque<Tensor<1>>,
    momentum: f64,
}

impl ModuleMapper for Blend {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let s = self
            .source
            .pop_front()
            .expect("EMA source and target have the same structure");
        let m = self.momentum;
        param.map(|t| {
            let shape = t.shape();
            (t.detach().mul_scalar(m) + s.reshape(shape).mul_scalar(1.0 - m)).detach()
        })
    }
}

/// `target ← m · target + (1 − m) · source`, parameter by parameter in traversal order (DINO,
/// Caron et al. 2021, §3.1; official `update_moving_average`).
/// `momentum = 0` copies `source`; the result never takes part in autodiff.
pub fn ema_update<M: Module>(target: M, source: &M, momentum: f64) -> M {
    let mut collect = Collect(VecDeque::new());
    source.visit(&mut collect);
    target.map(&mut Blend {
        source: collect.0,
        momentum,
    })
}

/// The official linear ramp of the EMA momentum from `start` to `end` over the run: the update
/// after step `step` uses `start + (end − start) · step / total` (Sparsh's `momentum_scheduler`
/// of I-JEPA and V-JEPA; I-JEPA, Assran et al. 2023, §4), held at `end` past `total`.
pub fn momentum_at(start: f64, end: f64, step: usize, total: usize) -> f64 {
    start + (end - start) * (step as f64 / total.max(1) as f64).min(1.0)
}
