#!/usr/bin/env bash
# The GPU check in one call: on a machine with a GPU and no Rust toolchain, run the project's GPU
# paths from a prepared binary and write one JSON of results (and a Markdown summary).
#
#   scripts/gpu-check.sh prepare         # on the build machine: .gpu/ gets the stripped, xz-packed
#                                        # release binary and the Vulkan/EGL loader packages
#   scripts/gpu-check.sh run OUT         # on the GPU machine, from the checkout's root (.gpu/
#                                        # carried beside it): OUT/gpu-check.json, .md and .log
#
# `run` stages, in order, each under a time limit inside one overall budget (GPU_CHECK_SECONDS,
# default 540), so that a slow stage costs its own result and not the ones after it:
#   1. environment: nvidia-smi, the Vulkan loader (unpacked from .gpu/*.deb where the machine has
#      none) and `sparsh devices`;
#   2. parity: a rendered frame (the quick-start press, frame 60) on the CPU and on the GPU, and
#      one training step of each objective (`sparsh bench-train --parity`);
#   3. throughput: `sparsh bench-train` on wgpu — a 4096³ f32 matrix product and the reference
#      step (ViT tiny/small/base, 320×240, patch 16, batch 64) — and the same reference step in
#      PyTorch on the same GPU (`crates/sparsh-ssl/benches/torch_step.py`: fp32, TF32, bf16);
#   4. image formation: `sparsh bench-optics --device gpu` (CPU and GPU, with and without shadows,
#      320×240 and 640×480);
#   5. the recipes' own steps on wgpu: the four objectives at ViT-base on 320×240 (batch 32) and
#      `assets/ssl/mae_small_gpu.toml` (batch 64);
#   6. pretraining: `assets/ssl/pretrain_gpu_data.toml` generated on the machine's cores, MAE
#      ViT-small at 320×240 (`mae_small_gpu.toml`) for as many steps as the budget left allows,
#      then the force probe against random draws of the same encoder.
#
# GPU_CHECK_QUICK=1 shrinks every size (tiny recipes, small inputs, a few steps): the whole script
# end to end on a software adapter (Mesa's lavapipe) in a few minutes, as CI's machine can. The
# binary is $GPU_CHECK_SPARSH if set, else .gpu/sparsh.xz when prepared, else
# target/release/sparsh; GPU_CHECK_WORK (default /tmp/gpu-check) holds the intermediate files;
# GPU_CHECK_STAGE_FACTOR (default 1) multiplies every stage's time limit (a machine shared with
# other work).
set -uo pipefail

here=$(cd "$(dirname "$0")/.." && pwd)
caller=$PWD
cd "$here" || exit 1

prepare() {
    local bin=target/release/sparsh
    [ -x "$bin" ] || { echo "prepare: $bin missing: cargo build --release -p sparsh-cli" >&2; exit 1; }
    mkdir -p .gpu
    grep -qx '/.gpu/' .git/info/exclude 2>/dev/null || echo '/.gpu/' >>.git/info/exclude
    # the release binary keeps line tables (~165 MB); stripped it is ~86 MB, xz-packed ~15 MB,
    # inside the 64 MiB a call carries
    strip -o .gpu/sparsh "$bin" && xz -T0 -6 -f .gpu/sparsh || exit 1
    # the Vulkan/EGL loaders (the GPU machine has the NVIDIA driver but no loader)
    local lists=/tmp/gpu-check-apt
    mkdir -p "$lists/partial"
    local o=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=$lists -oAPT::Sandbox::User=root)
    apt-get "${o[@]}" update -qq >/dev/null &&
        (cd .gpu && apt-get "${o[@]}" download -qq libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2) ||
        { echo "prepare: could not download the loader packages" >&2; exit 1; }
    du -sh .gpu
}

if [ "${1:-}" = prepare ]; then
    prepare
    exit 0
fi
[ "${1:-}" = run ] && [ -n "${2:-}" ] || { sed -n '2,9p' "$0" >&2; exit 2; }

out=$(cd "$caller" && mkdir -p "$2" && cd "$2" && pwd) || exit 1
work=${GPU_CHECK_WORK:-/tmp/gpu-check}
rm -rf "$work" && mkdir -p "$work"
log=$out/gpu-check.log
: >"$log"
budget=${GPU_CHECK_SECONDS:-540}
quick=${GPU_CHECK_QUICK:-0}
start=$(date +%s)
say() { echo "[$(($(date +%s) - start)) s] $*" | tee -a "$log" >&2; }

# `stage NAME LIMIT CMD…`: runs CMD (stdout to $work/NAME.out, both streams to the log) for at
# most LIMIT seconds or what is left of the budget (keeping 15 s for the summary); records the
# exit status and seconds in $work/stages.tsv (124: timed out).
stage() {
    local name=$1 limit=$(($2 * ${GPU_CHECK_STAGE_FACTOR:-1}))
    shift 2
    local left=$((budget - ($(date +%s) - start) - 15))
    [ "$limit" -gt "$left" ] && limit=$left
    if [ "$limit" -lt 5 ]; then
        say "$name: skipped (budget spent)"
        printf '%s\t%s\t%s\t%s\n' "$name" skipped 0 0 >>"$work/stages.tsv"
        return 1
    fi
    say "$name: up to $limit s: $*"
    local t0 rc ms
    t0=$(date +%s%N)
    timeout -k 5 "$limit" "$@" 2>>"$log" | tee "$work/$name.out" >>"$log"
    rc=${PIPESTATUS[0]}
    ms=$((($(date +%s%N) - t0) / 1000000))
    printf '%s\t%s\t%s\t%s\n' "$name" "$rc" "$ms" "$limit" >>"$work/stages.tsv"
    say "$name: exit $rc after $((ms / 1000)) s"
    return $rc
}

# --- 1. environment -------------------------------------------------------------------------
if [ -n "${GPU_CHECK_SPARSH:-}" ]; then
    sparsh=$GPU_CHECK_SPARSH
elif [ -f .gpu/sparsh.xz ]; then
    xz -dc .gpu/sparsh.xz >"$work/sparsh" && chmod +x "$work/sparsh"
    sparsh=$work/sparsh
else
    sparsh=$here/target/release/sparsh
fi
[ -x "$sparsh" ] || { say "no sparsh binary: run \`scripts/gpu-check.sh prepare\` on the build machine"; exit 1; }
if ! ldconfig -p 2>/dev/null | grep -q 'libvulkan.so.1'; then
    if ls .gpu/*.deb >/dev/null 2>&1; then
        say "no Vulkan loader: unpacking .gpu/*.deb"
        for f in .gpu/*.deb; do dpkg -x "$f" /; done
        ldconfig
    else
        say "no Vulkan loader and no .gpu/*.deb to unpack"
    fi
fi
icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
if [ -z "${VK_DRIVER_FILES:-}" ] && [ -f "$icd" ] && ! ls /usr/share/vulkan/icd.d/nvidia* /etc/vulkan/icd.d/nvidia* >/dev/null 2>&1; then
    export VK_DRIVER_FILES=$icd
    export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
fi
threads=$(nproc)
stage nvidia_smi 10 nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv,noheader
stage devices 30 "$sparsh" devices
stage torch_version 30 python3 -c 'import torch; print(torch.__version__, torch.cuda.is_available() and torch.cuda.get_device_name(0))'
cuda=0
grep -q ' NVIDIA\| H100\| H200' "$work/torch_version.out" 2>/dev/null && cuda=1

# sizes: the check's, or GPU_CHECK_QUICK's for a software adapter
if [ "$quick" = 1 ]; then
    input=48x32 patch=8 batch=4 sizes=tiny gemm=256 warm=1 timed=2
    recipes=(assets/ssl/mae_tiny_cpu.toml) recipe_batch=4
    # a recipe of the quick sizes: 2 blocks on 32×24, a short probe
    pre_recipe=$work/mae_quick.toml pre_data=assets/ssl/pretrain_tiny_data.toml
    sed -e 's/^img_size = .*/img_size = [32, 24]/' -e 's/^depth = .*/depth = 2/' \
        -e 's/^batch_size = .*/batch_size = 8/' -e 's/^probe_max_samples = .*/probe_max_samples = 96/' \
        -e 's/^probe_epochs = .*/probe_epochs = 3/' assets/ssl/mae_tiny_cpu.toml >"$pre_recipe"
    optics_repeats=1 probe_seeds=2 random_inits=1 pre_steps_cap=4
else
    input=320x240 patch=16 batch=64 sizes=tiny,small,base gemm=4096 warm=3 timed=10
    recipes=(assets/ssl/mae_base.toml assets/ssl/dino_base.toml assets/ssl/ijepa_base.toml assets/ssl/vjepa_base.toml)
    recipe_batch=32
    pre_recipe=assets/ssl/mae_small_gpu.toml pre_data=assets/ssl/pretrain_gpu_data.toml
    # the probe of 3 seeds and 3 random draws did not finish in 138 s on the H100
    optics_repeats=15 probe_seeds=1 random_inits=2 pre_steps_cap=800
fi
q=(--quiet)

# --- 2. parity ------------------------------------------------------------------------------
stage render_cpu 60 "$sparsh" "${q[@]}" render scenes/quickstart.toml --frame 60 --device cpu --png "$work/render_cpu.png"
stage render_gpu 60 "$sparsh" "${q[@]}" render scenes/quickstart.toml --frame 60 --device gpu --png "$work/render_gpu.png"
tiny=(assets/ssl/mae_tiny_cpu.toml assets/ssl/dino_tiny_cpu.toml assets/ssl/ijepa_tiny_cpu.toml assets/ssl/vjepa_tiny_cpu.toml)
stage step_parity 120 "$sparsh" "${q[@]}" bench-train --device wgpu --parity --warmup 0 --steps 1 --batch 4 \
    $(printf -- '--config %s ' "${tiny[@]}") --json "$work/step_parity.json"

# --- 3. throughput: burn on wgpu, then PyTorch on the same GPU ------------------------------
# one stage per size, so that a size the card cannot take costs only its own row
stage burn_gemm 60 "$sparsh" "${q[@]}" bench-train --device wgpu --gemm "$gemm" --json "$work/burn_gemm.json"
for size in ${sizes//,/ }; do
    stage "burn_reference_$size" 90 "$sparsh" "${q[@]}" bench-train --device wgpu --reference "$size" \
        --input "$input" --patch "$patch" --batch "$batch" --warmup "$warm" --steps "$timed" \
        --json "$work/burn_reference_$size.json"
done
if python3 -c 'import torch' 2>/dev/null; then
    tdev=cpu precisions=(fp32)
    [ "$cuda" = 1 ] && tdev=cuda precisions=(fp32 tf32 bf16)
    for size in ${sizes//,/ }; do
        for p in "${precisions[@]}"; do
            stage "torch_${size}_$p" 60 python3 crates/sparsh-ssl/benches/torch_step.py 0 "$size" "$warm" "$timed" \
                --device "$tdev" --precision "$p" --input "$input" --patch "$patch" --batch "$batch" \
                --json "$work/torch_${size}_$p.json"
        done
    done
else
    say "python3 cannot import torch: no PyTorch rows"
fi

# --- 4. image formation ---------------------------------------------------------------------
stage optics 90 "$sparsh" "${q[@]}" bench-optics --device gpu --calib assets/calib/gelsight \
    --repeats "$optics_repeats" --threads-list "$threads"

# --- 5. the recipes' steps ------------------------------------------------------------------
# one stage per recipe, so that a recipe the card cannot take at this batch (dino_base at 32 on
# the H100) costs only its own row
for recipe in "${recipes[@]}"; do
    r=$(basename "$recipe" .toml)
    stage "burn_recipe_$r" 60 "$sparsh" "${q[@]}" bench-train --device wgpu --batch "$recipe_batch" \
        --warmup 1 --steps 3 --config "$recipe" --json "$work/burn_recipe_$r.json"
done
stage burn_pretrain_recipe 60 "$sparsh" "${q[@]}" bench-train --device wgpu --warmup 1 --steps 3 \
    --config "$pre_recipe" --json "$work/burn_pretrain_recipe.json"

# --- 6. pretraining and the force probe -----------------------------------------------------
stage generate 60 "$sparsh" "${q[@]}" generate "$pre_data" --out "$work/data"
# steps: what a third of the budget left buys at the measured s/step, within the recipe's length
steps=$(python3 - "$work/burn_pretrain_recipe.json" "$budget" "$start" "$pre_steps_cap" <<'EOF'
import json, sys, time
try:
    s = json.load(open(sys.argv[1]))["rows"][0]["seconds_per_step"]
except Exception:
    s = None
left = int(sys.argv[2]) - (time.time() - int(sys.argv[3])) - 15
cap = int(sys.argv[4])
print(max(1, min(cap, int(0.5 * left / s))) if s else 1)
EOF
)
say "pretraining $steps steps of $pre_recipe"
stage pretrain 400 "$sparsh" "${q[@]}" pretrain --config "$pre_recipe" --data "$work/data" \
    --out "$work/run" --max-steps "$steps" --device wgpu
stage probe 300 "$sparsh" "${q[@]}" probe --config "$pre_recipe" --data "$work/data" \
    --encoder "$work/run/encoder.safetensors" --probe-seeds "$probe_seeds" \
    --random-inits "$random_inits" --device wgpu

# --- summary --------------------------------------------------------------------------------
python3 - "$work" "$out" "$steps" <<'EOF'
import glob, json, os, sys

work, out, steps = sys.argv[1], sys.argv[2], int(sys.argv[3])
def text(name):
    try:
        return open(os.path.join(work, name + ".out")).read()
    except OSError:
        return ""
def load(path):
    try:
        return json.load(open(path))
    except (OSError, ValueError):
        return None

result = {"stages": [], "environment": {}, "render_parity": None}
for line in open(os.path.join(work, "stages.tsv")):
    name, rc, secs, limit = line.rstrip("\n").split("\t")
    result["stages"].append({"stage": name, "exit": rc, "seconds": int(secs) / 1e3, "limit_s": int(limit)})
result["environment"] = {
    "gpu": text("nvidia_smi").strip(),
    "sparsh_devices": text("devices").strip().splitlines(),
    "torch": text("torch_version").strip(),
}
try:
    import numpy as np
    from PIL import Image
    a = np.asarray(Image.open(os.path.join(work, "render_cpu.png")), dtype=np.float64)
    b = np.asarray(Image.open(os.path.join(work, "render_gpu.png")), dtype=np.float64)
    d = np.abs(a - b)
    result["render_parity"] = {
        "frame": "scenes/quickstart.toml frame 60",
        "mean_abs_levels": float(d.mean()),
        "max_abs_levels": float(d.max()),
        "pixels_off_by_more_than_1": float((d.max(axis=-1) > 1).mean()),
    }
except Exception as e:
    result["render_parity"] = {"error": str(e)}
for key in ("step_parity", "burn_gemm", "burn_pretrain_recipe"):
    result[key] = load(os.path.join(work, key + ".json"))
result["burn_recipes"] = [load(p) for p in sorted(glob.glob(os.path.join(work, "burn_recipe_*.json")))]
result["burn_reference"] = [load(p) for p in sorted(glob.glob(os.path.join(work, "burn_reference_*.json")))]
result["torch_reference"] = [load(p) for p in sorted(glob.glob(os.path.join(work, "torch_*.json")))]
result["optics"] = text("optics")
result["pretrain"] = {"steps": steps, "log": (open(os.path.join(work, "run", "log.csv")).read()
                      if os.path.exists(os.path.join(work, "run", "log.csv")) else "")}
result["probe"] = text("probe")
tmp = os.path.join(out, "gpu-check.json.tmp")
json.dump(result, open(tmp, "w"), indent=1)
os.replace(tmp, os.path.join(out, "gpu-check.json"))

md = ["# GPU check", "", "Environment: " + json.dumps(result["environment"]), "",
      "| stage | exit | seconds | limit |", "|---|---|---|---|"]
md += [f"| {s['stage']} | {s['exit']} | {s['seconds']:.1f} | {s['limit_s']} |" for s in result["stages"]]
md += ["", "Render parity: " + json.dumps(result["render_parity"]), ""]
outs = lambda pattern: sorted(os.path.basename(p)[:-4] for p in glob.glob(os.path.join(work, pattern)))
names = (["step_parity", "burn_gemm"] + outs("burn_reference_*.out") + outs("burn_recipe_*.out")
         + ["burn_pretrain_recipe", "optics", "probe"])
for key in names:
    t = text(key)
    if t:
        md += [f"## {key}", "", t, ""]
rows = [t for t in result["torch_reference"] if t]
if rows:
    md += ["## torch_reference", "", "| ViT | precision | device | input | batch | s/step | images/s |", "|---|---|---|---|---|---|---|"]
    md += [f"| {t['size']} | {t['precision']} | {t['device']} | {t['input']} | {t['batch']} | {t['seconds_per_step']:.4f} | {t['images_per_second']:.1f} |" for t in rows]
open(os.path.join(out, "gpu-check.md"), "w").write("\n".join(md) + "\n")
EOF
say "done: $out/gpu-check.json, gpu-check.md, gpu-check.log"
