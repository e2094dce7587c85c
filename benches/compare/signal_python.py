"""What a scientist would otherwise run for fwlidar's signal chain, timed per waveform.

The same problem sizes as the criterion benchmarks (benches/deconvolve.rs, nnls.rs,
decompose.rs): a 256-sample return at 1 ns, a 16 ns FWHM Gaussian system response with taps to
+-3 sigma (41 taps), three echoes plus uniform noise.

- Richardson-Lucy, 20 iterations: skimage.restoration.richardson_lucy (1-D, clip=False).
- NNLS: scipy.optimize.nnls on the dense 256x256 convolution matrix.
- Wiener fused with a low-pass: numpy.fft (one forward, one inverse, kernel spectrum per call).
- Decomposition of a 3-echo waveform: scipy.optimize.curve_fit with a sum of 3 Gaussians.

Prints the median time per waveform of each.
"""
import sys
import timeit

import numpy as np
import scipy
import scipy.optimize
import skimage
from skimage.restoration import richardson_lucy

N = 256
FWHM = 16.0
SIGMA = FWHM / 2.35482
HALF = int(np.ceil(3 * SIGMA))
TAPS = np.exp(-0.5 * (np.arange(-HALF, HALF + 1) / SIGMA) ** 2)
TAPS /= TAPS.sum()
RNG = np.random.default_rng(20120601)


def waveform():
    truth = np.zeros(N)
    truth[[60, 100, 112]] = [40.0, 25.0, 20.0]
    y = np.convolve(truth, TAPS, mode="same") + RNG.uniform(-1.0, 1.0, N)
    return y


def conv_matrix():
    a = np.zeros((N, N))
    for i in range(N):
        for j, t in enumerate(TAPS):
            src = i + HALF - j
            if 0 <= src < N:
                a[i, src] = t
    return a


def wiener(y, noise=0.58, cutoff_ghz=0.2, dt=1.0):
    n = 2 * N
    k = np.zeros(n)
    k[: len(TAPS)] = TAPS
    k = np.roll(k, -HALF)
    P = np.fft.rfft(y, n)
    R = np.fft.rfft(k)
    S2 = np.abs(P) ** 2
    N2 = n * noise ** 2
    sigma = P * np.conj(R) / (np.abs(R) ** 2 + N2 / np.maximum(S2, 1e-12))
    sigma[np.arange(len(sigma)) / (n * dt) > cutoff_ghz] = 0
    return np.fft.irfft(sigma, n)[:N]


def gauss3(t, *p):
    out = np.zeros_like(t)
    for a, mu, s in zip(p[0::3], p[1::3], p[2::3]):
        out += a * np.exp(-0.5 * ((t - mu) / s) ** 2)
    return out


def median_us(f, number):
    runs = timeit.repeat(f, number=number, repeat=9)
    per = sorted(r / number for r in runs)
    return per[len(per) // 2] * 1e6


def main():
    y = waveform()
    yp = np.clip(y, 0, None)
    a = conv_matrix()
    t = np.arange(N, dtype=float)
    blurred = np.convolve(np.where(np.isin(np.arange(N), [60, 100, 112]), 30.0, 0.0),
                          np.exp(-0.5 * (np.arange(-20, 21) / 4.0) ** 2), mode="same")
    p0 = [30, 60, 4, 30, 100, 4, 30, 112, 4]
    print(f"versions: numpy {np.__version__}, scipy {scipy.__version__}, "
          f"scikit-image {skimage.__version__}, python {sys.version.split()[0]}")
    print(f"skimage richardson_lucy 20 it: {median_us(lambda: richardson_lucy(yp, TAPS, num_iter=20, clip=False), 200):.1f} us")
    print(f"scipy.optimize.nnls dense:     {median_us(lambda: scipy.optimize.nnls(a, y), 5):.1f} us")
    print(f"numpy fft wiener + low-pass:   {median_us(lambda: wiener(y), 2000):.1f} us")
    print(f"scipy curve_fit 3 gaussians:   {median_us(lambda: scipy.optimize.curve_fit(gauss3, t, blurred, p0=p0), 50):.1f} us")


if __name__ == "__main__":
    main()
