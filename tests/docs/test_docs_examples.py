"""Every `dqm` command line in README.md, docs/*.md and deploy/README.md runs as written (issue 36).

The command lines are taken from the fenced (and 4-space indented) code blocks, with backslash
continuations joined and `&&` chains split. Each block runs in a fresh folder holding small stand-ins
for the inputs the docs name (images/, photos/, dataset/, features.npz, robot0.npz, all.npz, ...),
its lines in order, as `dqm.cli.main` runs them; a line's own outputs are removed before it runs
(the docs show lines one can type in a row; the output policy refuses existing outputs). Every line
must exit 0.

A block preceded by ``<!-- not run in CI: REASON -->`` (several hosts, a router and camera nodes,
the shared data's minutes-long regenerations) is only parsed: each of its lines must be accepted
by the real parser, so that a renamed option still fails here.
"""
from __future__ import annotations

import re
import shlex
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional

import numpy as np
import pytest

from dqm import io, synthetic
from dqm.cli import _command_parser, build_parser, contradiction, join_negative_values, main

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", ROOT / "deploy" / "README.md"] + sorted((ROOT / "docs").glob("*.md"))
MARK = re.compile(r"<!--\s*not run in CI:\s*(.+?)\s*-->")
#: the options that name a command's outputs (removed before the line runs); the rest are inputs
OUTPUTS = {"extract": ("out",), "import": ("out",), "match": ("out", "tracks_csv"),
           "export": ("database", "matches", "pairs", "features", "tracks"), "plot": ("out", "out_dir"),
           "split": ("out",), "scene": ("out",), "evaluate": ("out_dir",), "run": ("out", "report"),
           "sfm": ("out",), "experiment": ("out_dir", "img_dir"), "stream": ("out",),
           "coordinator": ("out", "clusters")}


@dataclass
class Block:
    path: Path
    line: int
    skip: Optional[str]
    commands: List[tuple] = field(default_factory=list)  # (line number, argv)

    @property
    def name(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


def _argvs(text: str) -> List[List[str]]:
    """The dqm command lines of one shell line (`a && b`), each as argv without the leading ``dqm``."""
    out = []
    for part in text.split("&&"):
        words = shlex.split(part, comments=True)
        if words and words[0] == "dqm":
            out.append(words[1:])
    return out


def doc_blocks() -> List[Block]:
    """The code blocks with dqm command lines: fenced ones (no language, or a shell) and 4-space indented ones."""
    blocks = []
    for path in DOCS:
        lines = path.read_text().splitlines()
        skip, fenced, block = None, False, None
        k = 0
        while k < len(lines):
            raw, s = lines[k], lines[k].strip()
            if s.startswith("```"):
                if not fenced:
                    lang = s[3:].strip()
                    block = Block(path, k + 1, skip) if lang in ("", "sh", "bash", "shell") else None
                    skip = None
                elif block is not None:
                    blocks.append(block)
                    block = None
                fenced = not fenced
            elif not fenced and MARK.search(s):
                skip = MARK.search(s).group(1)
            elif not fenced and raw.startswith("    ") and s.startswith("dqm "):
                if block is None:
                    block = Block(path, k + 1, skip)
                    skip = None
                    blocks.append(block)
            elif not fenced and (not s or not raw.startswith("    ")):
                block = None  # an indented block ends at a blank or unindented line
            start = k
            while (fenced or raw.startswith("    ")) and s.endswith("\\") and k + 1 < len(lines):
                k += 1  # a continued line, whatever command it continues
                s = s[:-1] + " " + lines[k].strip()
            if block is not None and s.startswith("dqm "):
                block.commands.extend((start + 1, argv) for argv in _argvs(s))
            k += 1
    return [b for b in blocks if b.commands]


BLOCKS = doc_blocks()
PARSER = build_parser()


def _parse(argv: List[str]):
    argv = join_negative_values(PARSER, argv)
    args = PARSER.parse_args(argv)
    sub = _command_parser(PARSER, args.command)
    assert contradiction(sub, argv) is None, argv
    return args


def test_the_docs_hold_command_lines_and_name_what_is_not_run():
    n_run = sum(len(b.commands) for b in BLOCKS if not b.skip)
    n_marked = sum(len(b.commands) for b in BLOCKS if b.skip)
    assert n_run >= 30 and n_marked >= 1, (n_run, n_marked)
    print(f"{n_run} command lines run, {n_marked} marked as not run in CI, in {len(BLOCKS)} blocks")


@pytest.mark.parametrize("block", [b for b in BLOCKS if b.skip], ids=lambda b: b.name)
def test_a_marked_line_is_still_accepted_by_the_parser(block):
    for line, argv in block.commands:
        if any(w in ("...",) or w.startswith("[") for w in argv):
            continue  # a synopsis (docs/runtime.md): OPTION [VALUE] notation, not a command
        try:
            _parse(argv)
        except SystemExit:
            pytest.fail(f"{block.path.name}:{line}: dqm {' '.join(argv)} is refused by the parser")


@pytest.fixture(scope="module")
def stand_ins(tmp_path_factory):
    """Small inputs under the names the docs use."""
    d = tmp_path_factory.mktemp("standins")
    assert main(["scene", str(d / "images"), "--images", "3", "--size", "160", "200", "--seed", "5"]) == 0
    for name in ("photos", "frames"):
        shutil.copytree(d / "images", d / name)
    for seq in ("seq1", "seq2"):
        shutil.copytree(d / "images", d / "dataset" / seq)
    (d / "dataset" / "train.txt").write_text("seq1/img1.png\nseq1/img2.png\nseq2/img3.png\n")
    ds = synthetic.sift_like(n_images=8, n_points=120, noise=0.35, seed=0)
    fs = io.FeatureSet(ds.descriptors, ds.image_ids, point_ids=ds.point_ids)
    for name in ("features.npz", "all.npz"):
        io.save_features(d / name, fs)
    for k in range(2):
        rows = np.flatnonzero(ds.image_ids % 2 == k)
        io.save_features(d / f"robot{k}.npz", io.FeatureSet(ds.descriptors[rows], ds.image_ids[rows] // 2))
        (d / f"robot{k}.txt").write_text("".join(f"{i}\n" for i in range(k, 8, 2)))
    big = synthetic.sized(4000, seed=1)
    io.save_features(d / "big.npz", io.FeatureSet(big.descriptors, big.image_ids))
    (d / "docs").mkdir()
    shutil.copy(ROOT / "docs" / "evaluation.json", d / "docs" / "evaluation.json")
    try:  # a database of COLMAP's own feature extraction (the lines that match in place)
        import pycolmap
    except ImportError:
        pass
    else:
        pycolmap.extract_features(str(d / "database.db"), str(d / "images"))
    return d


def _outputs(args) -> List[str]:
    return [getattr(args, dest) for dest in OUTPUTS.get(args.command, ())
            if isinstance(getattr(args, dest, None), str)
            and not (args.command == "coordinator" and dest == "clusters" and args.no_clusters)]


@pytest.mark.parametrize("block", [b for b in BLOCKS if not b.skip], ids=lambda b: b.name)
def test_every_line_runs_as_written(block, stand_ins, tmp_path, monkeypatch, capsys):
    pytest.importorskip("pycolmap")
    pytest.importorskip("h5py")
    work = tmp_path / "work"
    shutil.copytree(stand_ins, work)
    monkeypatch.chdir(work)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    for name in ("clusters.npz", "c.npz"):  # CLUSTERS files name their images by absolute path: this folder's
        assert main(["match", "images", "--out", name, "--quiet", "--max-features", "120"]) == 0
    for line, argv in block.commands:
        args = _parse(argv)
        for out in _outputs(args):
            p = work / out
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
        capsys.readouterr()
        code = main(argv)
        captured = capsys.readouterr()
        assert code == 0, f"{block.path.name}:{line}: dqm {' '.join(argv)} exited {code}: {captured.err[-1500:]}"
        if "-v" in argv[:1]:
            assert captured.err.strip(), f"{block.path.name}:{line}: -v said nothing"
