"""Times libtorch's conv1d against oneDNN's convolution forced (`torch.mkldnn_convolution`) for
the ValueFunction's layer shapes at batch 1, 8 and 64 on one thread, and prints the largest
difference between the two (0 where libtorch already takes oneDNN). BENCHMARKS.md, issue 38,
session 26: why a batch of one is not given oneDNN. Run: .venv/bin/python tests/bench/conv1d_paths.py
"""
import time

import torch

# (in channels, out channels, kernel, stride, padding, length): the ValueFunction (widths 64,
# 64, 128, 128) over horizon 32.
SHAPES = [(64, 64, 5, 1, 2, 32), (128, 128, 5, 1, 2, 16), (128, 128, 3, 2, 1, 16),
          (128, 128, 5, 1, 2, 8), (128, 128, 5, 1, 2, 4), (128, 64, 5, 1, 2, 4)]


def best_us(f, rounds=5, n=100):
    for _ in range(20):
        f()
    best = float("inf")
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(n):
            f()
        best = min(best, (time.perf_counter() - start) / n * 1e6)
    return best


def main():
    torch.set_num_threads(1)
    torch.manual_seed(0)
    print("| batch | in, out, kernel, stride, padding, length | conv1d us | oneDNN us | max diff |")
    print("|---|---|---|---|---|")
    for batch in (1, 8, 64):
        for ci, co, k, s, p, length in SHAPES:
            x, w, b = torch.randn(batch, ci, length), torch.randn(co, ci, k), torch.randn(co)
            plain = best_us(lambda: torch.conv1d(x, w, b, s, p))
            forced = best_us(lambda: torch.mkldnn_convolution(x, w, b, [p], [s], [1], 1))
            diff = (torch.mkldnn_convolution(x, w, b, [p], [s], [1], 1) - torch.conv1d(x, w, b, s, p)).abs().max()
            print(f"| {batch} | {ci}, {co}, {k}, {s}, {p}, {length} | {plain:.1f} | {forced:.1f} | {diff.item():.1e} |")


if __name__ == "__main__":
    main()
