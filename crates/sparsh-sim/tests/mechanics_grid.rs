//! The mechanics grid: a margin beyond the camera's view keeps contacts that leave the view
//! whole, and a coarser stride keeps the physics.

use std::path::Path;

use sparsh_scene::Scene;
use sparsh_sim::Simulator;

fn scene(solver: &str, stride: usize, margin_mm: f64, x_mm: f64) -> Scene {
    let text = format!(
        r#"
solver = "{solver}"
mechanics_stride = {stride}
mechanics_margin_mm = {margin_mm}
[sensor]
preset = "digit"
width_px = 96
height_px = 64
mm_per_px = 0.1
[indenter]
shape = "sphere"
radius_mm = 3.0
[[trajectory]]
time_s = 0.0
position_mm = [{x_mm}, 0.0, -0.4]
"#
    );
    Scene::parse(Path::new("margin.toml"), text).unwrap()
}

fn normal_force_n(scene: Scene) -> (f64, usize) {
    let mut sim = Simulator::new(scene).unwrap();
    let frame = sim.next_frame().unwrap().unwrap();
    let in_view = frame.fields.contact.iter().filter(|&&c| c).count();
    (frame.fields.force_n[2], in_view)
}

/// Translation invariance: a contact centred on the view's edge carries the same load as one
/// centred in the view, once the margin holds the part outside the view.
#[test]
fn contact_leaving_the_view_keeps_its_whole_force() {
    for solver in ["geometric", "halfspace"] {
        let (centred, in_view_centred) = normal_force_n(scene(solver, 2, 3.0, 0.0));
        let (at_edge, in_view_edge) = normal_force_n(scene(solver, 2, 3.0, 4.8));
        assert!(
            in_view_edge < in_view_centred * 2 / 3,
            "{solver}: contact should leave the view"
        );
        assert!(
            (at_edge / centred - 1.0).abs() < 1e-3,
            "{solver}: {at_edge} N at the edge vs {centred} N centred"
        );
    }
}

/// A coarser mechanics grid changes the Hertz load little: 3 mm sphere, 0.4 mm deep.
#[test]
fn stride_two_keeps_the_hertz_load() {
    let (fine, _) = normal_force_n(scene("halfspace", 1, 2.0, 0.0));
    let (coarse, _) = normal_force_n(scene("halfspace", 2, 2.0, 0.0));
    assert!((coarse / fine - 1.0).abs() < 0.01, "{coarse} vs {fine}");
}
