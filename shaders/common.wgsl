// Bindings and helpers shared by the image-formation shaders (prepended to each model's source).
// One invocation per pixel; the surface arrives as f32 on the sensor grid, row-major.

struct Params {
    width: u32,
    height: u32,
    // Number of lights.
    lights: u32,
    // Table nodes per normal component (calibrated).
    nodes: u32,
    // Shadow samples per ray; 0 casts no shadows.
    shadow_steps: u32,
    // 1 with a perspective camera at (0, 0, camera_z_mm), 0 for an orthographic one.
    perspective: u32,
    // Shadow tiles are 2^tile_shift cells on a side; 0 takes no tile shortcuts.
    tile_shift: u32,
    // Index in `surface` of the tile bounds: block maximum height (mm), steepest slopes along x
    // and y, per tile, row-major.
    tile_offset: u32,
    // Grid cell edge (mm).
    cell_mm: f32,
    // Photometric gain from radiance to 0–255 units.
    gain: f32,
    // Blinn–Phong weight and exponent.
    specular: f32,
    shininess: f32,
    camera_z_mm: f32,
    max_march_mm: f32,
    led_radius_mm: f32,
    // Highest point of this frame's height field h = −u_z (mm).
    max_height_mm: f32,
    // Bound on the f32 error of a sampled height against the tile bounds (mm).
    height_tol_mm: f32,
    unused0: f32,
    unused1: f32,
    unused2: f32,
}

@group(0) @binding(0) var<uniform> params: Params;
// Normal displacement u_z (mm), then the model's further fields (lateral u_x, u_y), then with
// shadows the tile bounds (from `tile_offset`).
@group(0) @binding(1) var<storage, read> surface: array<f32>;
// The model's constant data: background (RGB 0–255) per pixel first, then model tables.
@group(0) @binding(2) var<storage, read> model: array<vec4<f32>>;
// The image before rounding (RGB, 0–255 scale; w unused).
@group(0) @binding(3) var<storage, read_write> image: array<vec4<f32>>;

fn pixel_count() -> u32 {
    return params.width * params.height;
}

fn uz_at(i: u32, j: u32) -> f32 {
    return surface[j * params.width + i];
}

// Centre of cell i along x and of row j along y (mm).
fn x_mm(i: u32) -> f32 {
    return (f32(i) + 0.5 - f32(params.width) / 2.0) * params.cell_mm;
}

fn y_mm(j: u32) -> f32 {
    return (f32(j) + 0.5 - f32(params.height) / 2.0) * params.cell_mm;
}

// ∇u_z: central differences inside, one-sided at the border (like numpy.gradient).
fn gradient(i: u32, j: u32) -> vec2<f32> {
    let il = max(i, 1u) - 1u;
    let ir = min(i + 1u, params.width - 1u);
    let ju = max(j, 1u) - 1u;
    let jd = min(j + 1u, params.height - 1u);
    let dx = f32(max(ir - il, 1u)) * params.cell_mm;
    let dy = f32(max(jd - ju, 1u)) * params.cell_mm;
    return vec2<f32>((uz_at(ir, j) - uz_at(il, j)) / dx, (uz_at(i, jd) - uz_at(i, ju)) / dy);
}

// Height h = −u_z (mm) at (x, y) mm, bilinear between cell centres, held beyond the outer ones
// (crates/sparsh-optics/src/shadow.rs, sample_height_mm).
fn sample_height(x: f32, y: f32) -> f32 {
    let fx = clamp(x / params.cell_mm + f32(params.width) / 2.0 - 0.5, 0.0, f32(params.width - 1u));
    let fy = clamp(y / params.cell_mm + f32(params.height) / 2.0 - 0.5, 0.0, f32(params.height - 1u));
    let i0 = u32(floor(fx));
    let j0 = u32(floor(fy));
    let i1 = min(i0 + 1u, params.width - 1u);
    let j1 = min(j0 + 1u, params.height - 1u);
    let tx = fx - f32(i0);
    let ty = fy - f32(j0);
    let top = -uz_at(i0, j0) * (1.0 - tx) - uz_at(i1, j0) * tx;
    let bottom = -uz_at(i0, j1) * (1.0 - tx) - uz_at(i1, j1) * tx;
    return top * (1.0 - ty) + bottom * ty;
}

// Occluder slopes up to m_c − LIT_MARGIN_RAD·(1 + m_c²) are at least LIT_MARGIN_RAD below the
// LED's edge in angle: enough for the penumbra's three atan (4096 ULP each in WGSL, ≤ 4.9e-4 rad
// below π/2) to give v = 1 exactly, so the tile shortcuts skip only rays this march finds lit.
const LIT_MARGIN_RAD: f32 = 2e-3;

// Visible fraction of a light at `light` = (x, y, height) mm from surface point p = (x, y,
// height) mm: march `shadow_steps` samples toward it, highest occluder slope m, clearance
// θ = atan r − atan m, linear penumbra across the LED's angular radius (shadow.rs,
// light_visibility, with its tile shortcuts).
fn visibility(p: vec3<f32>, light: vec3<f32>) -> f32 {
    let d = light.xy - p.xy;
    let reach = length(d);
    let rise = light.z - p.z;
    if (reach < 1e-9 || rise <= 0.0) {
        return 1.0;
    }
    let slope = rise / reach;
    // tan of the LED's angular radius; occluder slopes up to
    // m_c = tan(atan(slope) - α) = (slope - tan α)/(1 + slope·tan α) leave the whole LED in view.
    let tan_half_angle = params.led_radius_mm / length(vec2<f32>(reach, rise));
    var march = min(reach, params.max_march_mm);
    // the conservative m_c of the shortcuts (see LIT_MARGIN_RAD), 0 for none
    var lit_rate = 0.0;
    if (slope > tan_half_angle) {
        let clear_slope = (slope - tan_half_angle) / (1.0 + slope * tan_half_angle);
        march = min(march, (params.max_height_mm - p.z) / clear_slope);
        lit_rate = clear_slope - LIT_MARGIN_RAD * (1.0 + clear_slope * clear_slope);
    }
    if (march <= 0.0) {
        return 1.0;
    }
    let steps = params.shadow_steps;
    let dt = march / f32(steps);
    let dir = d / reach;
    // Samples first..=last: outside them, probe intervals proven clear (shadow.rs).
    var first = 1u;
    var last = steps;
    if (params.tile_shift > 0u && lit_rate > 0.0) {
        let shift = params.tile_shift;
        let tile = f32(1u << shift);
        let tile_mm = tile * params.cell_mm;
        let tiles_x = (params.width + (1u << shift) - 1u) >> shift;
        let probes = u32(ceil(march / tile_mm));
        let c = vec2<f32>(
            p.x / params.cell_mm + f32(params.width) / 2.0 - 0.5,
            p.y / params.cell_mm + f32(params.height) / 2.0 - 0.5,
        );
        let cell_max = vec2<f32>(f32(params.width - 1u), f32(params.height - 1u));
        // A sampled height may exceed the bounds by height_tol_mm: samples from t ≥ dt rise
        // faster than the bound by at most height_tol_mm / dt.
        let tol = params.height_tol_mm;
        let rate_limit = lit_rate - tol / dt;
        var rise_rate = 0.0;
        // failing probes first_fail..=last_fail; none while first_fail > last_fail
        var first_fail = probes;
        var last_fail = 0u;
        for (var j = 0u; j < probes; j++) {
            let s = f32(j) + 0.5;
            let f = vec2<u32>(clamp(c + s * tile * dir, vec2<f32>(0.0), cell_max));
            let b = params.tile_offset + 3u * ((f.y >> shift) * tiles_x + (f.x >> shift));
            rise_rate = max(rise_rate, abs(dir.x) * surface[b + 1u] + abs(dir.y) * surface[b + 2u]);
            // the interval's samples lie at t ≥ max(dt, j·Δ)
            let cone = p.z + max(dt, f32(j) * tile_mm) * lit_rate;
            if (rise_rate > rate_limit && surface[b] + tol > cone) {
                first_fail = min(first_fail, j);
                last_fail = j;
            }
        }
        if (first_fail > last_fail) {
            return 1.0;
        }
        first = max(u32(ceil(f32(first_fail) * tile_mm / dt)), 1u);
        // the last probe's interval reaches the march's end, sample `steps` (however the f32
        // quotients round)
        if (last_fail + 1u < probes) {
            last = min(u32(floor(f32(last_fail + 1u) * tile_mm / dt)), steps);
        }
    }
    var occluder = -3.4e38;
    for (var k = first; k <= last; k++) {
        let t = f32(k) * dt;
        let h = sample_height(p.x + t * dir.x, p.y + t * dir.y);
        occluder = max(occluder, (h - p.z) / t);
    }
    let clearance = atan(slope) - atan(occluder);
    let half_angle = atan(tan_half_angle);
    if (half_angle > 0.0) {
        return clamp(0.5 + 0.5 * clearance / half_angle, 0.0, 1.0);
    }
    return select(0.0, 1.0, clearance >= 0.0);
}

// Light k: (position (mm, camera frame), intensity) and (colour, 0), stored from `offset`.
fn light_position(offset: u32, k: u32) -> vec4<f32> {
    return model[offset + 2u * k];
}

fn light_colour(offset: u32, k: u32) -> vec3<f32> {
    return model[offset + 2u * k + 1u].rgb;
}

// Visible fraction of light k from pixel (i, j) of the undisplaced grid, 1 without shadows.
fn shadow_of(offset: u32, k: u32, i: u32, j: u32) -> f32 {
    if (params.shadow_steps == 0u) {
        return 1.0;
    }
    let l = light_position(offset, k).xyz;
    let p = vec3<f32>(x_mm(i), y_mm(j), -uz_at(i, j));
    return visibility(p, vec3<f32>(l.x, l.y, -l.z));
}
