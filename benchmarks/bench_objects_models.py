"""Cost of the object-query models on this machine: PE-Core-L14-336 (keyframe and text embeddings)
and SAM 3 (text-prompted masks), full size, seeded random weights (the cost does not depend on the
values), float32, CPU.

    python benchmarks/bench_objects_models.py [--threads 2] [--images 8] [--sam3-repeats 2]

Each model runs in its own child process, so that its peak memory (the process's resident
high-water mark, ``VmHWM``, weights included) is its own:

- PE-Core: ``make_embedder("pe-core-l14-336", random_init=True)``; one warm-up call, then the median
  of ``--images`` single-image calls (a 640x480 frame squashed to 336x336) and one call on
  ``--images`` images at once (per image), and the same for texts (one phrase; eight phrases at once).
- SAM 3: ``make_segmenter(random_init=True)`` (``transformers.Sam3Model`` at its released
  configuration, 1008x1008 input); one warm-up call, then the median of ``--sam3-repeats`` calls of
  ``segment(frame, "red mug")``.

Results go to ``benchmarks/results/objects_models.md``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time

from harness import date_text, load_average, peak_rss_bytes, result_file, torch_machine, write_report

PHRASES = ["red mug", "a wooden chair", "the laptop on the desk", "potted plant", "keyboard", "a book",
           "the monitor", "black office chair with wheels"]


def one_and_batched(embed, items: list) -> tuple[float, float]:
    """Seconds per item of ``embed`` (a list in, embeddings out): the median over the items one at a
    time, and one call on all of them divided by their count; one warm-up call first."""
    embed(items[:1])
    single = []
    for item in items:
        start = time.perf_counter()
        embed([item])
        single.append(time.perf_counter() - start)
    start = time.perf_counter()
    embed(items)
    return statistics.median(single), (time.perf_counter() - start) / len(items)


def frame(seed: int = 0):
    import numpy as np

    return np.random.default_rng(seed).integers(0, 256, (480, 640, 3), dtype=np.uint8)


def child_pe(threads: int, images: int) -> dict:
    import torch

    torch.set_num_threads(threads)
    from sl4slam.objects.embedder import make_embedder

    start = time.perf_counter()
    embedder = make_embedder("pe-core-l14-336", random_init=True, batch=images)
    build = time.perf_counter() - start
    frames = [frame(i) for i in range(images)]
    single, batched = one_and_batched(embedder.embed_images, frames)
    text_single, text_batched = one_and_batched(embedder.embed_texts, PHRASES)
    return {"build_s": build, "image_s": single, "image_batched_s": batched,
            "text_s": text_single, "text_batched_s": text_batched,
            "parameters": sum(p.numel() for p in embedder.model.parameters()), "peak_rss": peak_rss_bytes()}


def child_sam3(threads: int, repeats: int) -> dict:
    import torch

    torch.set_num_threads(threads)
    from sl4slam.objects.sam3 import make_segmenter

    start = time.perf_counter()
    segmenter = make_segmenter(random_init=True)
    build = time.perf_counter() - start
    image = frame(1)
    start = time.perf_counter()
    segmenter.segment(image, "red mug")
    first = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        segmenter.segment(image, "red mug")
        times.append(time.perf_counter() - start)
    return {"build_s": build, "first_s": first, "image_s": statistics.median(times), "repeats": repeats,
            "parameters": sum(p.numel() for p in segmenter.model.parameters()), "peak_rss": peak_rss_bytes()}


def in_child(part: str, args: argparse.Namespace) -> dict:
    command = [sys.executable, __file__, "--child", part, "--threads", str(args.threads), "--images", str(args.images),
               "--sam3-repeats", str(args.sam3_repeats)]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{part} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--images", type=int, default=8)
    parser.add_argument("--sam3-repeats", type=int, default=2)
    parser.add_argument("--child", choices=("pe", "sam3"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        record = child_pe(args.threads, args.images) if args.child == "pe" else child_sam3(args.threads, args.sam3_repeats)
        print(json.dumps(record))
        return
    load_before = load_average()
    pe, sam3 = in_child("pe", args), in_child("sam3", args)
    load_after = load_average()
    gib = 1024 ** 3
    lines = ["## Object-query models: cost on the CPU", "",
             f"Machine: {torch_machine()}; {date_text('%Y-%m-%d')}. {args.threads} threads; float32; seeded random "
             "weights, full size (the cost does not depend on the values).",
             f"Command: `python benchmarks/bench_objects_models.py --threads {args.threads} --images {args.images} "
             f"--sam3-repeats {args.sam3_repeats}`",
             f"1-minute load average {load_before:.1f} at the start and {load_after:.1f} at the end (the machine is "
             "shared: times include contention).", "",
             "| model | what | seconds | peak memory |", "|---|---|---|---|",
             f"| PE-Core-L14-336 ({pe['parameters'] / 1e6:.0f} M) | one keyframe image (336x336) | {pe['image_s']:.3f} "
             f"| {pe['peak_rss'] / gib:.2f} GiB |",
             f"| | per image, {args.images} at once | {pe['image_batched_s']:.3f} | |",
             f"| | one phrase | {pe['text_s']:.3f} | |",
             f"| | per phrase, {len(PHRASES)} at once | {pe['text_batched_s']:.3f} | |",
             f"| | building the model (random init) | {pe['build_s']:.1f} | |",
             f"| SAM 3 ({sam3['parameters'] / 1e6:.0f} M) | one image and phrase (1008x1008), median of "
             f"{sam3['repeats']} | {sam3['image_s']:.2f} | {sam3['peak_rss'] / gib:.2f} GiB |",
             f"| | first call | {sam3['first_s']:.2f} | |",
             f"| | building the model (random init) | {sam3['build_s']:.1f} | |", ""]
    write_report(result_file("objects_models"), lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
