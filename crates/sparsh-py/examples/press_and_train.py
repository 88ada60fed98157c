"""Simulate a press, write it as a dataset, train one PyTorch step on it through the Dataset class."""
import os, sys, torch, sparsh
from sparsh.torch import GeneratedDataset
scene, out = os.path.join(os.environ["SPARSH"], "scenes", "quickstart.toml"), sys.argv[1] if len(sys.argv) > 1 else "out/quickstart_py"
frames = list(sparsh.Scene(scene).simulate())  # image, fields (p qx qy ux uy uz contact slip) and label of every frame
print(f"{len(frames)} frames; at the deepest press F = {max(f['label']['force_n'][2] for f in frames):.3f} N, peak p = {max(f['fields']['p'].max() for f in frames):.1f} kPa")
print(sparsh.generate(scene, out, force=True)["notes"])
loader = torch.utils.data.DataLoader(GeneratedDataset(out), batch_size=16, shuffle=True, num_workers=2)  # I_t ⊕ I_t-5, official preprocessing
model = torch.nn.Sequential(torch.nn.Conv2d(6, 16, 8, stride=8), torch.nn.ReLU(), torch.nn.AdaptiveAvgPool2d(1), torch.nn.Flatten(), torch.nn.Linear(16, 3))
batch = next(iter(loader)); loss = torch.nn.functional.mse_loss(model(batch["image"]), batch["force_n"]); loss.backward(); torch.optim.Adam(model.parameters()).step()
print(f"one training step on a batch of {len(batch['frame'])}: loss {loss.item():.4f}")
