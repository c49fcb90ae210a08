//! The element-wise passes of the hand-written generator: a layer's scale, shift and
//! activation and its backward pass, and the generator's 2x upsampling and its adjoint. The
//! hot loops are compiled also for AVX2 and AVX-512 and chosen at run time; no step is fused
//! or reordered, so every build gives the same bytes.

use multiversion::multiversion;

/// A layer's output from its product y, row by row (`[pixels, channels]`): per channel c,
/// out = act(y d_c + b_c), act a leaky slope `(above, below)` 0. Compiled also for wider
/// vector units and chosen at run time (the result is the same: no step is fused or
/// reordered).
#[multiversion(targets("x86_64+avx2", "x86_64+avx512f"))]
pub(super) fn scale_shift_activate(
    y: &[f32],
    (d, bias): (&[f32], &[f32]),
    (above, below): (f32, f32),
    out: &mut [f32],
) {
    for (row, y) in out.chunks_exact_mut(d.len()).zip(y.chunks_exact(d.len())) {
        for (((o, y), d), b) in row.iter_mut().zip(y).zip(d).zip(bias) {
            let z = y * d + b;
            *o = if z > 0.0 { above } else { below } * z;
        }
    }
}

/// Back through [`scale_shift_activate`]: turns `g` (the output's gradient) into y's in place
/// and adds the gradients of d and b into `gd`, `gb`.
#[multiversion(targets("x86_64+avx2", "x86_64+avx512f"))]
pub(super) fn scale_shift_activate_backward(
    y: &[f32],
    (d, bias): (&[f32], &[f32]),
    (above, below): (f32, f32),
    g: &mut [f32],
    (gd, gb): (&mut [f32], &mut [f32]),
) {
    for (g, y) in g.chunks_exact_mut(d.len()).zip(y.chunks_exact(d.len())) {
        let terms = g.iter_mut().zip(y).zip(d).zip(bias);
        for ((((g, y), d), b), (gd, gb)) in terms.zip(gd.iter_mut().zip(gb.iter_mut())) {
            let gz = *g * if y * d + b > 0.0 { above } else { below };
            *gd += gz * y;
            *gb += gz;
            *g = gz * d;
        }
    }
}

/// Neighbours of index `i` of `n` along an axis: circular (azimuth) or replicated (elevation).
fn neighbours(i: usize, n: usize, circular: bool) -> (usize, usize) {
    if circular {
        ((i + n - 1) % n, (i + 1) % n)
    } else {
        (i.saturating_sub(1), (i + 1).min(n - 1))
    }
}

/// [`crate::model::layers::upsample2x`] along one axis of `[outer, n, inner]` data:
/// out[2i] = x[i-1] / 4 + 3 x[i] / 4, out[2i+1] = 3 x[i] / 4 + x[i+1] / 4.
#[multiversion(targets("x86_64+avx2", "x86_64+avx512f"))]
fn upsample_axis(x: &[f32], (outer, n, inner): (usize, usize, usize), circular: bool) -> Vec<f32> {
    let mut out = Vec::with_capacity(2 * x.len());
    for rows in x.chunks_exact(n * inner).take(outer) {
        let row = |j: usize| &rows[j * inner..(j + 1) * inner];
        for i in 0..n {
            let (prev, next) = neighbours(i, n, circular);
            let (xp, xi, xn) = (row(prev), row(i), row(next));
            out.extend(xp.iter().zip(xi).map(|(p, x)| 0.25 * p + 0.75 * x));
            out.extend(xi.iter().zip(xn).map(|(x, n)| 0.75 * x + 0.25 * n));
        }
    }
    out
}

/// The adjoint (transpose) of [`upsample_axis`]: x[i] collects 3/4 of out[2i] and out[2i+1]
/// and 1/4 of out[2i+2] and out[2i-1] (at a replicated border, of its own pair again).
#[multiversion(targets("x86_64+avx2", "x86_64+avx512f"))]
fn upsample_axis_adjoint(
    g: &[f32],
    (outer, n, inner): (usize, usize, usize),
    circular: bool,
) -> Vec<f32> {
    let mut out = Vec::with_capacity(g.len() / 2);
    for rows in g.chunks_exact(2 * n * inner).take(outer) {
        let even = |j: usize| &rows[2 * j * inner..(2 * j + 1) * inner];
        let odd = |j: usize| &rows[(2 * j + 1) * inner..(2 * j + 2) * inner];
        for i in 0..n {
            let (a, b) = if circular {
                (even((i + 1) % n), odd((i + n - 1) % n))
            } else {
                let a = if i + 1 < n { even(i + 1) } else { odd(i) };
                let b = if i > 0 { odd(i - 1) } else { even(i) };
                (a, b)
            };
            let terms = even(i).iter().zip(odd(i)).zip(a.iter().zip(b));
            out.extend(terms.map(|((e, o), (a, b))| 0.75 * (e + o) + 0.25 * (a + b)));
        }
    }
    out
}

/// `[h, w, ch]` -> `[2h, 2w, ch]`, as the generator upsamples.
pub(super) fn upsample2x(x: &[f32], (h, w): (usize, usize), ch: usize) -> Vec<f32> {
    let wide = upsample_axis(x, (h, w, ch), true);
    upsample_axis(&wide, (1, h, 2 * w * ch), false)
}

/// The adjoint of [`upsample2x`]: `[2h, 2w, ch]` -> `[h, w, ch]`.
pub(super) fn upsample2x_adjoint(g: &[f32], (h, w): (usize, usize), ch: usize) -> Vec<f32> {
    let narrow = upsample_axis_adjoint(g, (1, h, 2 * w * ch), false);
    upsample_axis_adjoint(&narrow, (h, w, ch), true)
}
