"""Reads a `sparsh export --format sparsh-pkl` directory exactly as facebookresearch/sparsh
(@fee6a05) does, and prints what its loaders see as JSON.

The reading logic is transcribed from the official repository, function by function:
- tactile_ssl/data/digit/utils.py: compute_diff, load_bin_image, load_sample_from_buf,
  get_bg_img (with the one-line patch of DIGIT_BGS_OBJECTS the sparsh book gives), load_pickle_dataset,
  load_dataset_forces_digit_gelsight;
- tactile_ssl/data/vision_based_forces_slip_probes.py: VisionForceSlipDataset (__init__,
  get_map_idx2traj, _get_slip_labels, _get_force_slip_labels, _get_tactile_images);
- tactile_ssl/data/vision_tactile.py: VisionTactileBackboneDataset (no augmentation);
- train.py get_dataloaders_vision_based and train_task.py get_dataloader_digit (look_in_folder).
torch, torchvision and cv2 are replaced by numpy and PIL where they compute the same thing:
cv2.rotate(ROTATE_90_CLOCKWISE) is np.rot90(k=-1), cv2.imread + COLOR_BGR2RGB is PIL's RGB,
transforms.ToTensor is HWC uint8 -> CHW float / 255. Resize is left out: the check reads frames at
the exported resolution, where the official resize is the identity.

usage: official_loaders.py EXPORT_DIR OUT_JSON IMAGE_F32
  IMAGE_F32: the official input of the force/slip sample with the largest normal force (CHW
  float32, raw, I_t then I_t-5), for the caller to compare with its own preprocessing.
"""

import io
import json
import os
import pickle
import sys
from glob import glob

import numpy as np
import yaml
from PIL import Image

# ---- tactile_ssl/data/digit/utils.py ----

DIGIT_BGS_OBJECTS = {"004_sugar_box": 0}  # the official table; none of its objects is exported


def compute_diff(img1, img2, offset=0.0):
    img1 = np.int32(img1)
    img2 = np.int32(img2)
    diff = img1 - img2
    diff = diff / 255.0 + offset
    diff = np.clip(diff, 0.0, 1.0)
    diff = np.uint8(diff * 255.0)
    return diff


def get_bg_img(config, sensor_type, dataset_name, remove_bg=True):
    bg = None
    if remove_bg:
        path_bgs = config["path_bgs"]
        if sensor_type == "digit":
            # the patched line: objects outside the official table name their own background
            bg_id = DIGIT_BGS_OBJECTS.get(dataset_name.split("/")[0], dataset_name.split("/")[0])
            bg = np.array(Image.open("{0}/bg_{1}.jpg".format(path_bgs, bg_id)).convert("RGB"))
        elif sensor_type == "gelsight_mini":
            bg = np.array(Image.open("{0}/bg_gs.jpg".format(path_bgs)).convert("RGB"))
        else:
            raise ValueError("Unknown sensor type")
    return bg


def load_pickle_dataset(file_dataset):
    with open(file_dataset, "rb") as f:
        all_frames = pickle.load(f)
    return all_frames


def load_bin_image(io_buf):
    img = Image.open(io.BytesIO(io_buf))
    img = np.array(img)
    return img


def load_sample_from_buf(io_buf, img_bg=None):
    img = load_bin_image(io_buf) if isinstance(io_buf, bytes) else io_buf
    assert isinstance(img, np.ndarray), ValueError("Image should be a numpy array")
    assert img.shape[2] == 3, ValueError("Image should have 3 channels")
    if img_bg is not None:
        img = compute_diff(img, img_bg, offset=0.5)
    h, w, _ = img.shape
    if h < w:
        img = np.rot90(img, k=-1)  # cv2.rotate(img, cv2.ROTATE_90_CLOCKWISE)
    h, w, _ = img.shape
    r = 4 / 3
    if h / w != r:
        h2, w2 = int(h / r), w
        img = img[int((h - h2) / 2) : int((h + h2) / 2), int((w - w2) / 2) : int((w + w2) / 2)]
    return np.ascontiguousarray(img)


def to_tensor(img):
    return np.transpose(img, (2, 0, 1)).astype(np.float32) / 255.0


def load_dataset_forces_digit_gelsight(config, dataset_name, sensor):
    path_data = os.path.join(config["path_dataset"], dataset_name)
    path_force_slip = os.path.join(path_data, "dataset_slip_forces.pkl")
    path_images = sorted(glob(os.path.join(path_data, f"dataset_{sensor}*")))
    dataset_images = []
    for p in path_images:
        with open(p, "rb") as f:
            dataset_images.extend(pickle.load(f))
    with open(path_force_slip, "rb") as f:
        dataset_force_slip = pickle.load(f)
    return dataset_images, dataset_force_slip


# ---- tactile_ssl/data/vision_based_forces_slip_probes.py ----


class VisionForceSlipDataset:
    def __init__(self, config, dataset_name):
        self.config = config
        self.slip_horizon = config["slip_horizon"]
        self.remove_bg = config.get("remove_bg", False)
        frame_stride = config["frame_stride"]
        self.num_frames = config["num_frames"]
        self.frames_concat_idx = np.arange(0, self.num_frames * frame_stride, frame_stride)
        self.frames, dataset_force_slip = load_dataset_forces_digit_gelsight(
            config, dataset_name, config["sensor"]
        )
        self.in_contact = dataset_force_slip["in_contact"]
        self.trajectories = dataset_force_slip["trajectories"]
        self.idx2traj, self.traj2idx, self.slip_labels = self.get_map_idx2traj()
        self.bg = None
        if self.remove_bg:
            idx_bg = np.where(self.in_contact == 0)[0][0]
            self.bg = load_bin_image(self.frames[idx_bg])
        self.max_abs_forceXYZ = config["max_abs_forceXYZ"]
        self.max_delta_forceXYZ = config["max_delta_forceXYZ"]

    def get_map_idx2traj(self):
        slip_labels_all = []
        idx2traj = {}
        traj2idx = {}
        idx = -1
        for trajectory_i in self.trajectories.keys():
            traj2idx[trajectory_i] = []
            t_idxs = self.trajectories[trajectory_i]["indexes"][5:]
            for sample in range(len(t_idxs)):
                idx += 1
                traj2idx[trajectory_i].append(idx)
                idx2traj[idx] = {}
                idx2traj[idx]["trajectory"] = trajectory_i
                idx2traj[idx]["sample"] = sample
                slip_label = self._get_slip_labels(trajectory_i, sample)
                idx2traj[idx]["slip_horizon_labels"] = slip_label
                slip_labels_all.append(0 if slip_label.sum() == 0 else 1)
        return idx2traj, traj2idx, np.array(slip_labels_all)

    def _get_slip_labels(self, trajectory_i, sample):
        slip_labels = self.trajectories[trajectory_i]["slip_label"]
        len_trajectory = len(slip_labels)
        t = sample + np.arange(0, self.slip_horizon + 1)
        t = np.clip(t, 0, len_trajectory - 1)
        return slip_labels[t].astype(int)

    def __len__(self):
        return len(self.idx2traj)

    def __getitem__(self, idx):
        idx_trajectory = self.idx2traj[idx]["trajectory"]
        idx_sample = self.idx2traj[idx]["sample"]
        label, abs_force, delta_force = self._get_force_slip_labels(idx, idx_trajectory, idx_sample)
        return {
            "trajectory": int(idx_trajectory),
            "sample": int(idx_sample),
            "image": self._get_tactile_images(idx_trajectory, idx_sample),
            "force_n": self.trajectories[idx_trajectory]["forces"][idx_sample].tolist(),
            "force": abs_force.tolist(),
            "delta_force": delta_force.tolist(),
            "slip_label": int(label),
        }

    def _get_force_slip_labels(self, idx, idx_trajectory, idx_sample):
        slip_horizon_labels = self.idx2traj[idx]["slip_horizon_labels"]
        label = 0 if slip_horizon_labels.sum() == 0 else 1
        len_trajectory = len(self.trajectories[idx_trajectory]["indexes"])
        idx_sample_prev = np.clip(idx_sample - self.frames_concat_idx[-1], 0, len_trajectory - 1)
        f_curr = self.trajectories[idx_trajectory]["forces"][idx_sample]
        f_prev = self.trajectories[idx_trajectory]["forces"][idx_sample_prev]
        delta_forces = f_curr - f_prev
        delta_forces = delta_forces / self.max_delta_forceXYZ
        delta_forces = np.clip(delta_forces, -1.0, 1.0)
        abs_forces = self.trajectories[idx_trajectory]["forces"][idx_sample]
        abs_forces = abs_forces / self.max_abs_forceXYZ
        abs_forces = np.clip(abs_forces, -1.0, 1.0)
        return label, abs_forces, delta_forces

    def _get_tactile_images(self, idx_trajectory, idx_sample):
        t_indexes = self.trajectories[idx_trajectory]["indexes"]
        len_trajectory = len(t_indexes)
        sample_images = []
        for i in self.frames_concat_idx:
            idx_sample = np.clip(idx_sample - i, 0, len_trajectory - 1)
            frame_index = t_indexes[idx_sample]
            image = load_sample_from_buf(self.frames[frame_index], self.bg)
            sample_images.append(to_tensor(image))
        return np.concatenate(sample_images, axis=0)  # concat_ch_img


# ---- tactile_ssl/data/vision_tactile.py ----


class VisionTactileBackboneDataset:
    def __init__(self, config, dataset_name):
        self.sensor_type = config["sensor"]
        self.remove_bg = config.get("remove_bg", False)
        file_dataset = f"{config['path_dataset']}/{dataset_name}.pkl"
        self.frames = load_pickle_dataset(file_dataset)
        self.total_frames = len(self.frames)
        self.bg = get_bg_img(config, self.sensor_type, dataset_name, self.remove_bg)

    def __len__(self):
        return self.total_frames

    def first_input(self):
        return load_sample_from_buf(self.frames[0], self.bg)


# ---- train_task.py, train.py ----


def force_datasets(cfg, names):
    """get_dataloader_digit with look_in_folder."""
    out = []
    for obj in names:
        for f in sorted(os.listdir(os.path.join(cfg["path_dataset"], obj))):
            out.append((obj + "/" + f.split(".")[0], VisionForceSlipDataset(cfg, obj + "/" + f.split(".")[0])))
    return out


def ssl_datasets(data_cfg):
    """get_dataloaders_vision_based."""
    train, val = [], []
    for sensor_cfg in data_cfg["sensor"]:
        cfg = dict(sensor_cfg["dataset"]["config"])
        cfg["remove_bg"] = data_cfg["remove_bg"] if cfg.get("remove_bg") == "${data.remove_bg}" else cfg.get("remove_bg")
        if sensor_cfg["type"] in ("digit", "gelsight_mini"):
            for obj in cfg["list_datasets"]:
                for d_id in cfg["dataset_ids_train"]:
                    train.append((obj + "/dataset_" + str(d_id), VisionTactileBackboneDataset(cfg, obj + "/dataset_" + str(d_id))))
                for d_id in cfg["dataset_ids_val"]:
                    val.append((obj + "/dataset_" + str(d_id), VisionTactileBackboneDataset(cfg, obj + "/dataset_" + str(d_id))))
        elif sensor_cfg["type"] == "gelsight":
            all_datasets = []
            for obj in cfg["list_datasets"]:
                for file in os.listdir(os.path.join(cfg["path_dataset"], obj)):
                    name = obj + "/" + file.split(".")[0]
                    all_datasets.append((name, VisionTactileBackboneDataset(cfg, name)))
            all_datasets = sorted(all_datasets, key=lambda x: len(x[1]), reverse=True)
            n = int(len(all_datasets) * cfg["train_val_split"])
            train += all_datasets[:n]
            val += all_datasets[n:]
    return train, val


def main():
    export, out_json, image_out = sys.argv[1:4]
    report = {"force": [], "ssl": {}}
    strongest = None
    for path in sorted(glob(os.path.join(export, "sparsh_force_slip_*.yaml"))):
        data_cfg = yaml.safe_load(open(path))
        cfg = dict(data_cfg["dataset"]["config"])
        cfg["sensor"] = data_cfg["sensor"]  # ${data.sensor}
        assert cfg["look_in_folder"] is True
        for split, names in (("train", cfg["list_datasets"]), ("test", cfg["list_datasets_test"])):
            for name, ds in force_datasets(cfg, names):
                for idx in range(len(ds)):
                    item = ds[idx]
                    image = item.pop("image")
                    assert image.shape[0] == 6, image.shape
                    item.update(split=split, batch=name, sensor=cfg["sensor"])
                    report["force"].append(item)
                    if strongest is None or item["force_n"][2] > strongest[0]["force_n"][2]:
                        strongest = (item, image)
    ssl_cfg = yaml.safe_load(open(os.path.join(export, "sparsh_ssl.yaml")))
    train, val = ssl_datasets(ssl_cfg)
    report["ssl"] = {
        "train": {name: len(ds) for name, ds in train},
        "val": {name: len(ds) for name, ds in val},
        "input_shapes": sorted({str(ds.first_input().shape) for _, ds in train + val}),
    }
    report["strongest"] = {k: strongest[0][k] for k in ("batch", "sample")}
    report["strongest"]["shape"] = list(strongest[1].shape)
    json.dump(report, open(out_json, "w"))
    strongest[1].astype(np.float32).tofile(image_out)


if __name__ == "__main__":
    main()
