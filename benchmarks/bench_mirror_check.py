"""Feasibility of a learned check for BlazePose's whole-body left/right flips (issue 19).

A small CNN sees a crop (64 px RGB) and two channels of its left and right landmarks, and scores
f(crop, landmarks) - f(crop, landmarks with left/right exchanged): above 0 says the landmarks are
mirrored. Labels need no 3D annotation: each crop's landmarks are put right against the
reference (the synthetic truth, or the fuse stage's bodies on a real scene) and shown both as
they are (0) and exchanged (1), and both again with the image flipped. Trained on the first 75 %
of frames, tested on the rest (all cameras). Prints per epoch the test AUC and how many of the
test's mirrored and unmirrored crops score above 0.5 and 0.8, beside the time.

    python benchmarks/bench_mirror_check.py workspace/demo synth 12
    python benchmarks/bench_mirror_check.py workspace/lab fused 12   # after `run fuse --scene lab`

2026-11-28 (docs in the closing note): test AUC up to 0.98 (demo) and 0.99 (lab), but it
overfits within a few epochs; not yet part of the pipeline.

2026-11-28, later: this split trains on every camera, so it measures a skill the pipeline cannot
use. Built as `train` would (training cameras and frames only, labels from the fused bodies,
early stopping on the last quarter of the training frames, a temperature and the training flip
rate as prior; tried as this CNN, as frozen LPIPS-AlexNet features with a conv head, and as
those features sampled at each landmark), the check called 30 of the lab's held-out camera's
unmirrored crops mirrored while finding 3 of 19 flips, and on the demo's held-out crops found
0 of 29 with 2-6 false (test AUC 0.65-0.70). A scene's 2 people in a few hundred crops teach
camera-specific looks, not facing. Reverted (commit 36c90ee holds the CNN version).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from benchmarks.cli import bench_parser
from benchmarks.flip_data import labelled_scene_crops
from gst.body.markers import BLAZEPOSE_MIRROR
from gst.train.views import heldout_frame_start

ap = bench_parser(__doc__)
ap.add_argument("workspace", type=Path, help="the scene's workspace folder (WS/<scene>)")
ap.add_argument(
    "reference",
    nargs="?",
    default="synth",
    choices=["synth", "fused"],
    help="what labels the crops: the synthetic truth, or the fuse stage's bodies (default synth)",
)
ap.add_argument("epochs", nargs="?", type=int, default=15, help="training epochs (default 15)")
args = ap.parse_args()
torch.manual_seed(0)
np.random.seed(0)
ws = args.workspace
ref = args.reference
crops, landmarks, sides = labelled_scene_crops(ws, "truth" if ref == "synth" else "fused")
ok = crops.truth["has_truth"].numpy()
lm = landmarks.numpy()
mir = sides < 0
N = len(lm)
frames = crops.frame.numpy()
cut = heldout_frame_start(crops.frame, 0.25)
train = ok & (frames < cut)
test = ok & (frames >= cut)
print(
    f"crops {N}, with ref {ok.sum()}, mirrored {mir.sum()} (train {mir[train].sum()} of "
    f"{train.sum()}, test {mir[test].sum()} of {test.sum()}), cut {cut}"
)

imgs = crops.images.float()
if imgs.max() > 2:
    imgs = imgs / 255.0
if imgs.shape[-1] == 3:
    imgs = imgs.permute(0, 3, 1, 2)
H, W = imgs.shape[-2:]
S = 64
scale = S / max(H, W)
imgs = F.interpolate(imgs, size=(round(H * scale), round(W * scale)), mode="area")
h, w = imgs.shape[-2:]
print("image", tuple(imgs.shape))
LEFT = [i for i in range(33) if BLAZEPOSE_MIRROR[i] != i and i % 2 == 1]  # left ids are odd
RIGHT = [int(BLAZEPOSE_MIRROR[i]) for i in LEFT]


def channels(lmk):
    """(N, 33, 3) crop px -> (N, 2, h, w) Gaussian blobs of left and right landmarks."""
    lmk = torch.as_tensor(lmk).float()
    ys, xs = torch.meshgrid(torch.arange(h).float(), torch.arange(w).float(), indexing="ij")
    out = []
    for ids in (LEFT, RIGHT):
        p = lmk[:, ids]
        u = p[..., 0] * scale
        v = p[..., 1] * scale
        c = torch.nan_to_num(p[..., 2], 0.0)
        u, v = torch.nan_to_num(u, -100), torch.nan_to_num(v, -100)
        g = torch.exp(
            -((xs - u[..., None, None]) ** 2 + (ys - v[..., None, None]) ** 2) / (2 * 1.5**2)
        )
        out.append((g * c[..., None, None]).amax(1))
    return torch.stack(out, 1)


class Net(nn.Module):
    def __init__(self):
        super().__init__()
        c = 32
        self.f = nn.Sequential(
            nn.Conv2d(5, c, 3, padding=1),
            nn.BatchNorm2d(c),
            nn.ReLU(),
            nn.MaxPool2d(2),
            nn.Conv2d(c, 2 * c, 3, padding=1),
            nn.BatchNorm2d(2 * c),
            nn.ReLU(),
            nn.MaxPool2d(2),
            nn.Conv2d(2 * c, 4 * c, 3, padding=1),
            nn.BatchNorm2d(4 * c),
            nn.ReLU(),
            nn.MaxPool2d(2),
            nn.Conv2d(4 * c, 4 * c, 3, padding=1),
            nn.BatchNorm2d(4 * c),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(1),
            nn.Flatten(),
            nn.Dropout(0.3),
            nn.Linear(4 * c, 1),
        )

    def forward(self, x):
        return self.f(x)[:, 0]


# Training examples: the crop's landmarks un-mirrored (label 0) and their mirror (label 1), and
# both with the image flipped horizontally (coords mirrored and labels exchanged: a valid body).
lm_true = lm.copy()
lm_true[mir] = lm[mir][:, BLAZEPOSE_MIRROR]


def hflip(im, lmk):
    l2 = lmk.copy()
    l2[..., 0] = (W - 1) - l2[..., 0]
    return im.flip(-1), l2[:, BLAZEPOSE_MIRROR]


tr = np.flatnonzero(train)
base_im = imgs[tr]
base_lm = lm_true[tr]
fim, flm = hflip(base_im, base_lm)
X_im = torch.cat([base_im, base_im, fim, fim])
X_lm = np.concatenate([base_lm, base_lm[:, BLAZEPOSE_MIRROR], flm, flm[:, BLAZEPOSE_MIRROR]])
Y = torch.tensor([0] * len(tr) + [1] * len(tr) + [0] * len(tr) + [1] * len(tr)).float()
X = torch.cat([X_im, channels(X_lm)], 1)
te = np.flatnonzero(test)
Xte = torch.cat([imgs[te], channels(lm[te])], 1)
Yte = mir[te]
net = Net()
opt = torch.optim.AdamW(net.parameters(), 2e-3, weight_decay=1e-3)
t0 = time.time()
epochs = args.epochs
for ep in range(epochs):
    net.train()
    perm = torch.randperm(len(X))
    tot = 0
    for b in range(0, len(X), 64):
        i = perm[b : b + 64]
        x = X[i]
        # brightness jitter + small shifts
        x = torch.cat([x[:, :3] * (0.8 + 0.4 * torch.rand(len(i), 1, 1, 1)), x[:, 3:]], 1)
        dx, dy = np.random.randint(-3, 4, 2)
        x = torch.roll(x, (int(dy), int(dx)), (2, 3))
        xm = torch.cat([x[:, :3], x[:, 4:5], x[:, 3:4]], 1)  # landmarks' labels exchanged
        loss = F.binary_cross_entropy_with_logits(net(x) - net(xm), Y[i])
        opt.zero_grad()
        loss.backward()
        opt.step()
        tot += loss.item() * len(i)
    net.eval()
    with torch.no_grad():
        Xm = torch.cat([Xte[:, :3], Xte[:, 4:5], Xte[:, 3:4]], 1)
        p = torch.sigmoid(net(Xte) - net(Xm)).numpy()
    pos, neg = p[Yte], p[~Yte]
    auc = (pos[:, None] > neg[None]).mean() if len(pos) and len(neg) else float("nan")
    print(
        f"epoch {ep} loss {tot / len(X):.3f} test AUC {auc:.3f}  mirrored p median "
        f"{np.median(pos) if len(pos) else 0:.2f}, others p>0.5 {np.sum(neg > 0.5)} "
        f"p>0.8 {np.sum(neg > 0.8)} mirrored p>0.5 {np.sum(pos > 0.5)} "
        f"p>0.8 {np.sum(pos > 0.8)} of {len(pos)} ({time.time() - t0:.0f} s)",
        flush=True,
    )
