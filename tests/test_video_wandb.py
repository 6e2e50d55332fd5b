"""Evaluation videos (evaluate.py --video) decoded back, and W&B tracking (--track, and evaluate.py --run of a tracked
run) readback from wandb's offline run files."""

import glob
import importlib.machinery
import importlib.util
import json
import os
import re
import signal
import subprocess
import sys

import imageio_ffmpeg
import numpy as np
import pytest
import torch

import p3o_atari_envpool as p3o
import ppo_atari_envpool as ppo
from helpers import ROOT, scalars

TINY = ["--env-id", "Breakout-v5", "--num-envs", "4", "--num-steps", "64", "--num-minibatches", "2"]
TINY += ["--update-epochs", "1", "--total-timesteps", "768", "--seed", "2"]  # 3 iterations


def train(algo, cwd, *extra, env=None):
    cmd = [sys.executable, os.path.join(ROOT, f"{algo}_atari_envpool.py"), *TINY, *extra]
    env = {**os.environ, "WANDB_MODE": "offline", "WANDB_SILENT": "true", **(env or {})}
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def decode(path):
    """(frames [n, height, width, 3], fps) of an MP4, decoded with the same library's ffmpeg."""
    reader = imageio_ffmpeg.read_frames(path)
    meta = next(reader)
    width, height = meta["size"]
    frames = np.stack([np.frombuffer(f, np.uint8).reshape(height, width, 3) for f in reader])
    return frames, meta["fps"]


def wandb_records(path):
    """The records of an offline W&B run file (`run-<id>.wandb`): wandb's own protobuf `Record` messages in
    LevelDB's log framing (a 7-byte header, 32 KiB blocks, each record split into chunks of crc32c, length,
    type). wandb 0.31 has no Python reader for this file, so the framing is read here."""
    from wandb.proto import wandb_internal_pb2

    data = open(path, "rb").read()
    assert data[:4] == b":W&B"
    pos, chunks, records = 7, b"", []
    while pos + 7 <= len(data):
        room = 32768 - pos % 32768
        length, kind = int.from_bytes(data[pos + 4 : pos + 6], "little"), data[pos + 6]
        if room < 7 or (length == 0 and kind == 0):  # a block's zero padding
            pos += room
            continue
        chunks += data[pos + 7 : pos + 7 + length]
        pos += 7 + length
        if kind in (1, 4):  # a FULL record, or the LAST chunk of one
            record = wandb_internal_pb2.Record()
            record.ParseFromString(chunks)
            records.append(record)
            chunks = b""
    return records


def offline_run(wandb_dir):
    """run id, config and history rows of each offline run under wandb_dir, oldest first."""
    runs = []
    for path in sorted(glob.glob(os.path.join(wandb_dir, "offline-run-*", "run-*.wandb"))):
        run = {"history": [], "config": {}}
        for record in wandb_records(path):
            kind = record.WhichOneof("record_type")
            if kind == "run":
                run["id"], run["name"] = record.run.run_id, record.run.display_name
                run["config"] = {item.key: json.loads(item.value_json) for item in record.run.config.update}
            elif kind == "history":
                row = {
                    item.key or "/".join(item.nested_key): json.loads(item.value_json) for item in record.history.item
                }
                run["history"].append(row)
        runs.append(run)
    return runs


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A P3O run with --capture-video and --track (offline): (cwd, run folder)."""
    cwd = tmp_path_factory.mktemp("tracked")
    proc = train("p3o", cwd, "--run-name", "v", "--track")
    assert proc.returncode == 0, proc.stderr[-3000:]
    evaluate = os.path.join(ROOT, "benchmark", "evaluate.py")
    env = {**os.environ, "WANDB_MODE": "offline", "WANDB_SILENT": "true"}
    cmd = [sys.executable, evaluate, "--run", "runs/v", "--episodes", "2", "--video"]
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return cwd, cwd / "runs" / "v"


def test_each_evaluation_game_is_a_colour_video_of_all_its_frames(tracked):
    _, run_dir = tracked
    report = json.loads((run_dir / "eval.json").read_text())
    assert sorted(os.listdir(run_dir / "videos")) == ["eval-game0.mp4", "eval-game1.mp4"]
    assert report["videos"] == [f"runs/v/videos/eval-game{i}.mp4" for i in range(2)]
    for game, length in enumerate(report["lengths"]):
        frames, fps = decode(str(run_dir / "videos" / f"eval-game{game}.mp4"))
        assert len(frames) == length > 50  # one frame per agent step of a full game (all lives)
        assert frames.shape[1:] == (210, 160, 3) and fps == 15
        assert frames.std() > 10  # not blank
        # colour: the channels differ (Breakout's coloured bricks), which a grey frame's would not
        assert np.abs(frames[..., 0].astype(int) - frames[..., 2].astype(int)).mean() > 5
        assert not np.array_equal(frames[0], frames[-1])  # the game moves


def test_video_changes_nothing_the_agent_sees(tmp_path):
    from benchmark import evaluate

    torch.manual_seed(0)
    agent = ppo.Agent(4)
    torch.manual_seed(1)
    plain = evaluate.play(agent, "Breakout-v5", 2, 100, False, torch.device("cpu"))
    torch.manual_seed(1)
    filmed = evaluate.play(agent, "Breakout-v5", 2, 100, False, torch.device("cpu"), str(tmp_path / "videos"))
    assert filmed.pop("videos") == [str(tmp_path / "videos" / f"eval-game{i}.mp4") for i in range(2)]
    assert filmed == plain


def test_tracked_run_mirrors_tensorboard_in_wandb(tracked):
    # the training and, after it, evaluate.py --run: two offline runs of one W&B run
    cwd, run_dir = tracked
    trained, evaluated = offline_run(str(cwd / "wandb"))
    assert trained["id"] == evaluated["id"] == (run_dir / "wandb_id").read_text()
    assert trained["name"] == evaluated["name"] == "v"
    assert trained["config"]["env_id"] == "Breakout-v5" and trained["config"]["ewma_alpha"] == 0.9
    points, history = scalars(run_dir), trained["history"] + evaluated["history"]
    for tag in ("charts/episodic_return", "losses/value_loss", "p3o/beta_mean", "eval/episodic_return"):
        logged = [v for _, v in points[tag]]
        mirrored = [row[tag] for row in history if tag in row]
        assert logged and np.allclose(mirrored, logged, rtol=1e-6), tag
    videos = {k: v for row in evaluated["history"] for k, v in row.items() if k.startswith("videos/")}
    assert videos["videos/eval-game0/_type"] == "video-file" and videos["videos/eval-game1/_type"] == "video-file"
    assert videos["videos/eval-game0/size"] == os.path.getsize(run_dir / "videos" / "eval-game0.mp4")


def test_a_resumed_tracked_run_continues_the_same_wandb_run(tmp_path):
    cmd = [sys.executable, os.path.join(ROOT, "ppo_atari_envpool.py"), *TINY, "--total-timesteps", "1280"]
    cmd += ["--run-name", "r", "--auto-resume", "--checkpoint-every", "0", "--track"]
    env = {**os.environ, "WANDB_MODE": "offline", "WANDB_SILENT": "true"}
    proc = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in proc.stdout:
        if line.startswith("iteration 2/"):
            proc.send_signal(signal.SIGTERM)
            break
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 128 + signal.SIGTERM, err[-3000:]
    first_id = (tmp_path / "runs" / "r" / "wandb_id").read_text()
    resumed = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert re.search(r"resuming runs/r after iteration \d", resumed.stdout)
    runs = offline_run(str(tmp_path / "wandb"))
    assert len(runs) == 2 and runs[0]["id"] == runs[1]["id"] == first_id
    # a new run in a new folder gets a W&B run of its own
    other = train("ppo", tmp_path, "--run-name", "other", "--track")
    assert other.returncode == 0, other.stderr[-3000:]
    assert (tmp_path / "runs" / "other" / "wandb_id").read_text() != first_id


def test_evaluate_script_writes_videos(tracked, tmp_path):
    _, run_dir = tracked
    script = os.path.join(ROOT, "benchmark", "evaluate.py")
    cmd = [sys.executable, script, "--model-path", str(run_dir / "checkpoint.pt"), "--episodes", "1"]
    proc = subprocess.run([*cmd, "--run-dir", str(tmp_path / "e"), "--video"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads((tmp_path / "e" / "eval.json").read_text())
    frames, _ = decode(report["videos"][0])
    assert len(frames) == report["lengths"][0] and frames.shape[1:] == (210, 160, 3)
    refused = subprocess.run([*cmd, "--video"], capture_output=True, text=True)
    assert refused.returncode == 1
    assert refused.stderr == "error: --video needs --run-dir, the folder whose videos/ the games are written to.\n"


@pytest.mark.parametrize("module", [ppo, p3o], ids=["ppo", "p3o"])
def test_track_without_wandb_is_refused(module, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    find_spec = importlib.util.find_spec
    # without wandb installed, python finds nothing, or, where an offline run left its ./wandb/ folder beside the
    # script, that folder as an empty namespace package (which is not wandb either)
    (tmp_path / "wandb").mkdir()
    leftover = importlib.machinery.PathFinder.find_spec("wandb", [str(tmp_path)])
    assert leftover is not None and leftover.origin is None
    # were the check passed, a tiny run would train, tracked by a disabled wandb, and return: the test fails fast
    monkeypatch.setenv("WANDB_MODE", "disabled")
    tiny = dict(num_envs=4, num_steps=16, num_minibatches=2, update_epochs=1, total_timesteps=64)
    for spec in (None, leftover):
        monkeypatch.setattr(
            importlib.util, "find_spec", lambda name, *a, s=spec: s if name == "wandb" else find_spec(name, *a)
        )
        with pytest.raises(SystemExit) as excinfo:
            module.main(module.Args(track=True, cuda=False, **tiny))
        assert (
            excinfo.value.code
            == "error: --track needs wandb: run with `uv run --extra wandb ...` (or `pip install wandb`)."
        )
    assert not (tmp_path / "runs").exists()


def test_track_without_a_wandb_login_is_one_sentence_before_training(tmp_path):
    # no API key anywhere (a fresh HOME, no WANDB_API_KEY) and not offline: wandb cannot start
    env = {k: v for k, v in os.environ.items() if not k.startswith("WANDB_")} | {"HOME": str(tmp_path), "NETRC": ""}
    cmd = [sys.executable, os.path.join(ROOT, "p3o_atari_envpool.py"), *TINY, "--track", "--no-cuda", "--run-name", "t"]
    proc = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error: W&B did not start (") and last.endswith(
        "); log in with `wandb login`, or set WANDB_MODE=offline."
    )
    assert "Traceback" not in proc.stderr and "iteration 1/" not in proc.stdout


def test_an_offline_runs_wandb_folder_is_git_ignored():
    """`WANDB_MODE=offline` leaves ./wandb/ beside the scripts: git must not offer it for a commit."""
    proc = subprocess.run(["git", "check-ignore", "-q", "wandb/offline-run-1/run-1.wandb"], cwd=ROOT)
    assert proc.returncode == 0
