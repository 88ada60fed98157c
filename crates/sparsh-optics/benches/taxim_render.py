"""Taxim 1.4.1 (JAX CPU) render time of one 640×480 GelSight frame, with and without shadows:
the baseline that `sparsh bench-optics` compares against (its TAXIM_640_MS constant).

    python3 -m venv /tmp/taxim && /tmp/taxim/bin/pip install taxim==1.4.1 'jax[cpu]'
    /tmp/taxim/bin/python crates/sparsh-optics/benches/taxim_render.py
    ./target/release/sparsh bench-optics --repeats 7 --threads-list 1 2   # right after, same load

Scene as in `bench-optics`: a 2 mm ball pressed to a 1.2 mm contact radius (depth
d = R − √(R² − a²) = 0.4 mm), centred (+1.0, −0.5) mm from the image centre, on Taxim's shipped
GelSight calibration (0.0295 mm/px). One warm-up render (JIT), then the median of 10; each timed
render ends with `block_until_ready()`, so the JAX work finishes inside the timer. JAX uses every
core, so compare with the 2-thread rows on a 2-core machine.
"""
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np
import taxim

TIMED = 10
BALL_RADIUS_MM = 2.0
CONTACT_RADIUS_MM = 1.2
DEPTH_MM = BALL_RADIUS_MM - np.sqrt(BALL_RADIUS_MM**2 - CONTACT_RADIUS_MM**2)
CENTRE_MM = (1.0, -0.5)  # x right, y up, from the image centre


def ball_height_map(width, height, mm_per_px):
    """Taxim's height map (mm, smaller = closer to the camera); the ball's lowest point is 0."""
    xs = (np.arange(width) - (width - 1) / 2) * mm_per_px - CENTRE_MM[0]
    ys = -((np.arange(height) - (height - 1) / 2) * mm_per_px) - CENTRE_MM[1]
    xx, yy = np.meshgrid(xs, ys)
    r2 = xx**2 + yy**2
    r = BALL_RADIUS_MM
    return np.where(r2 < r**2, r - np.sqrt(np.maximum(r**2 - r2, 0.0)), r).astype(np.float32)


def median_ms(render):
    render()
    times = []
    for _ in range(TIMED):
        start = time.perf_counter()
        render()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times)


def main():
    sim = taxim.Taxim(calib_folder=taxim.CALIB_GELSIGHT, backend="jax")
    heights = jax.device_put(
        jnp.asarray(ball_height_map(sim.width, sim.height, sim.sensor_params.pixmm))
    )
    print(f"taxim {taxim.__version__ if hasattr(taxim, '__version__') else '1.4.1'}, "
          f"jax {jax.__version__}, {sim.width}×{sim.height}, {jax.devices()}")
    for shadows in (True, False):
        ms = median_ms(
            lambda: sim.render_direct(
                heights, with_shadow=shadows, press_depth=DEPTH_MM
            ).block_until_ready()
        )
        print(f"shadows {'yes' if shadows else 'no'}: median {ms:.1f} ms per frame")


if __name__ == "__main__":
    main()
