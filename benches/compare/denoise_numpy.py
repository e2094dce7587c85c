"""What a scientist would otherwise run for fwlidar's denoise stage, timed the same way.

Per pulse (64-sample outgoing + 256-sample return at 1 ns, the pulse of benches/signal.rs):
counts -> volts, baseline = median of the first 8 samples, level shift, zero-padding to twice
the length, real FFT, zero every bin above 0.2 GHz, inverse FFT, noise level = mean |raw -
smoothed|. Once with numpy.fft and once with scipy.fft (the faster of the usual choices).

Run by benches/compare/run.sh beside `cargo bench --bench signal`; prints the median time per
pulse over repeated timeit runs.
"""
import sys
import timeit

import numpy as np
import scipy.fft


def cao_like_pulse():
    sigma = 16.0 / 2.35482
    i64 = np.arange(64)
    i256 = np.arange(256)
    g = lambda i, mu, a: a * np.exp(-0.5 * ((i - mu) / sigma) ** 2)
    ripple = lambda i: 3.0 * (((i * 7919) % 13) / 6.0 - 1.0)
    out = np.round(12.0 + g(i64, 32.0, 200.0) + ripple(i64)).astype(np.uint16)
    ret = np.round(12.0 + g(i256, 67.0, 40.0) + g(i256, 167.0, 36.0) + ripple(i256)).astype(np.uint16)
    return out, ret


def make_denoise(fft):
    def denoise_segment(counts, gain=0.004, offset=0.0, dt_ns=1.0, cutoff_ghz=0.2):
        v = offset + gain * counts.astype(np.float64)
        base = np.median(v[:8])
        x = v - base
        n = 2 * len(x)
        spec = fft.rfft(x, n)
        freqs = np.arange(len(spec)) / (n * dt_ns)
        spec[freqs > cutoff_ghz] = 0.0
        smooth = fft.irfft(spec, n)[: len(x)]
        noise = np.mean(np.abs(x - smooth))
        return smooth, base, noise

    def denoise_pulse(pulse):
        return [denoise_segment(s) for s in pulse]

    return denoise_pulse


def main():
    pulse = cao_like_pulse()
    for name, fft in (("numpy.fft", np.fft), ("scipy.fft", scipy.fft)):
        f = make_denoise(fft)
        f(pulse)
        number = 2000
        runs = timeit.repeat(lambda: f(pulse), number=number, repeat=15)
        per = sorted(r / number for r in runs)
        print(f"{name}: median {per[len(per) // 2] * 1e6:.2f} us per pulse "
              f"(numpy {np.__version__}, scipy {scipy.__version__}, python {sys.version.split()[0]})")


if __name__ == "__main__":
    main()
