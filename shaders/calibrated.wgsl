// Calibrated model (crates/sparsh-optics/src/calibrated.rs): I = bg + T₀(n) + x·T_x(n) + y·T_y(n),
// each T bilinear on an N × N table over the normal's lateral components (nx, ny) ∈ [−1, 1]²;
// with shadows each channel is scaled by 1 − Σ_l w_{l,ch}·(1 − v_l) (= Σ_l w_{l,ch} v_l as the
// shares sum to 1; light l's share of the flat gel's colour times its hidden fraction is lost),
// exactly 1 where every light is in view.
// surface: u_z; model: background | tables, index (b·N + v)·N + u for basis b (1, x, y) |
// light shares (lights per pixel) | lights.

fn table(b: u32, k: u32) -> vec3<f32> {
    let nodes = params.nodes;
    return model[pixel_count() + b * nodes * nodes + k].rgb;
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    if (id.x >= params.width || id.y >= params.height) {
        return;
    }
    let n_px = pixel_count();
    let c = id.y * params.width + id.x;
    let g = gradient(id.x, id.y);
    let n = g / sqrt(1.0 + dot(g, g));
    let x = (f32(id.x) + 0.5) / f32(params.width) - 0.5;
    let y = (f32(id.y) + 0.5) / f32(params.height) - 0.5;
    let nodes = params.nodes;
    let span = f32(nodes - 1u);
    let fu = clamp((n.x + 1.0) / 2.0 * span, 0.0, span);
    let fv = clamp((n.y + 1.0) / 2.0 * span, 0.0, span);
    let iu = min(u32(floor(fu)), nodes - 2u);
    let iv = min(u32(floor(fv)), nodes - 2u);
    let tu = fu - f32(iu);
    let tv = fv - f32(iv);
    let k = iv * nodes + iu;
    let w = vec4<f32>((1.0 - tu) * (1.0 - tv), tu * (1.0 - tv), (1.0 - tu) * tv, tu * tv);
    let basis = vec3<f32>(1.0, x, y);
    var colour = model[c].rgb;
    for (var b = 0u; b < 3u; b++) {
        let t = w.x * table(b, k) + w.y * table(b, k + 1u) + w.z * table(b, k + nodes)
            + w.w * table(b, k + nodes + 1u);
        colour += basis[b] * t;
    }
    if (params.shadow_steps > 0u) {
        let shares = n_px + 3u * nodes * nodes;
        let lights = shares + n_px * params.lights;
        var lost = vec3<f32>(0.0);
        for (var l = 0u; l < params.lights; l++) {
            let hidden = 1.0 - shadow_of(lights, l, id.x, id.y);
            lost += model[shares + c * params.lights + l].rgb * hidden;
        }
        colour *= vec3<f32>(1.0) - lost;
    }
    image[c] = vec4<f32>(colour, 0.0);
}
