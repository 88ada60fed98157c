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
    unused0: u32,
    unused1: u32,
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
}

@group(0) @binding(0) var<uniform> params: Params;
// Normal displacement u_z (mm), then the model's further fields (lateral u_x, u_y).
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

// Visible fraction of a light at `light` = (x, y, height) mm from surface point p = (x, y,
// height) mm: march `shadow_steps` samples toward it, highest occluder slope m, clearance
// θ = atan r − atan m, linear penumbra across the LED's angular radius (shadow.rs,
// light_visibility).
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
    if (slope > tan_half_angle) {
        let clear_slope = (slope - tan_half_angle) / (1.0 + slope * tan_half_angle);
        march = min(march, (params.max_height_mm - p.z) / clear_slope);
    }
    if (march <= 0.0) {
        return 1.0;
    }
    let dt = march / f32(params.shadow_steps);
    let dir = d / reach;
    var occluder = -3.4e38;
    for (var k = 1u; k <= params.shadow_steps; k++) {
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
