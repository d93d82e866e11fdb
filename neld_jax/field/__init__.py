"""The density field and how it renders LiDAR ranges: pure JAX, no I/O.

- `encoding`: the Fourier encoding with its surrogate gradient and coarse-to-fine window;
- `density`: the MLP from (position, view direction) to a density; `normalize`: the [-1, 1]^3 cube it lives in;
- `sampling`: where samples go along a ray; `rendering`: alpha compositing and the map range of a ray;
- `model`: per-scan poses and the field to rendered ranges; `losses`: the range and termination losses.
"""
