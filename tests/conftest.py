import os
import sys

# The whole suite runs on the CPU whatever the host has: the pinned numbers were recorded on the CPU, and a
# GPU would run TF32 convolutions. Set before torch initialises CUDA, and inherited by the scripts the tests
# start as subprocesses.
os.environ["CUDA_VISIBLE_DEVICES"] = ""
# wandb in the tests is offline and quiet, never the network
os.environ["WANDB_MODE"] = "offline"
os.environ["WANDB_SILENT"] = "true"

from helpers import ROOT  # noqa: E402  (after the environment above)

if ROOT not in sys.path:
    sys.path.insert(0, ROOT)
