// Photometric model (crates/sparsh-optics/src/photometric.rs): I = bg + g·V·(S(n) − S(n₀)), with
// S = Σ_l c_l v_l I_l [max(n·l̂, 0) + k_s max(n·ĥ, 0)^s] d₀²/|L − P|², d₀ = 10 mm, v_l the
// light's visible fraction (cast shadows) and V the cos⁴ vignetting.
// surface: u_z | u_x | u_y; model: background | flat-gel shading (rgb) and V (w) | lights.

// Radiance toward the camera under light k per unit light colour (photometric.rs, radiance).
fn radiance(n: vec3<f32>, p: vec3<f32>, view: vec3<f32>, light: vec4<f32>) -> f32 {
    let to_light = light.xyz - p;
    let d2 = dot(to_light, to_light);
    let l = to_light / sqrt(d2);
    let cos_l = dot(n, l);
    if (cos_l <= 0.0) {
        return 0.0;
    }
    var specular = 0.0;
    if (params.specular > 0.0) {
        let h = normalize(l + view);
        specular = params.specular * pow(max(dot(n, h), 0.0), params.shininess);
    }
    return light.w * (cos_l + specular) * 100.0 / d2;
}

@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    if (id.x >= params.width || id.y >= params.height) {
        return;
    }
    let n_px = pixel_count();
    let c = id.y * params.width + id.x;
    let g = gradient(id.x, id.y);
    // Normal of z = u_z(x, y) facing the camera (−z).
    let n = vec3<f32>(g.x, g.y, -1.0) / sqrt(g.x * g.x + g.y * g.y + 1.0);
    let p = vec3<f32>(
        x_mm(id.x) + surface[n_px + c],
        y_mm(id.y) + surface[2u * n_px + c],
        surface[c],
    );
    var view = vec3<f32>(0.0, 0.0, -1.0);
    if (params.perspective == 1u) {
        view = normalize(vec3<f32>(0.0, 0.0, params.camera_z_mm) - p);
    }
    let lights = 2u * n_px;
    var rgb = vec3<f32>(0.0);
    for (var k = 0u; k < params.lights; k++) {
        let e = shadow_of(lights, k, id.x, id.y) * radiance(n, p, view, light_position(lights, k));
        rgb += light_colour(lights, k) * e;
    }
    let flat = model[n_px + c];
    image[c] = vec4<f32>(model[c].rgb + params.gain * flat.w * (rgb - flat.rgb), 0.0);
}
