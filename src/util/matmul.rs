//! Single-threaded f32 matrix products on host slices: a safe face over the `gemm` crate for
//! code that runs its own passes over small dense tensors (one scan per thread, so each
//! product stays on the calling thread and its result does not depend on the thread count).
//! Products with a side of one or two rows or columns are written out by hand.

/// A read-only matrix inside a slice: element (r, c) is `data[r * row_stride + c * col_stride]`.
#[derive(Debug, Clone, Copy)]
pub struct View<'a> {
    data: &'a [f32],
    rows: usize,
    cols: usize,
    row_stride: usize,
    col_stride: usize,
}

impl<'a> View<'a> {
    /// A row-major `rows x cols` matrix.
    pub fn new(data: &'a [f32], rows: usize, cols: usize) -> Self {
        Self::strided(data, rows, cols, cols, 1)
    }

    /// Columns `start..start + cols` of a row-major matrix with `width` columns.
    pub fn columns(data: &'a [f32], rows: usize, width: usize, start: usize, cols: usize) -> Self {
        assert!(
            start + cols <= width,
            "columns {start}..{} of {width}",
            start + cols
        );
        Self::strided(&data[start.min(data.len())..], rows, cols, width, 1)
    }

    fn strided(
        data: &'a [f32],
        rows: usize,
        cols: usize,
        row_stride: usize,
        col_stride: usize,
    ) -> Self {
        if rows > 0 && cols > 0 {
            let last = (rows - 1) * row_stride + (cols - 1) * col_stride;
            assert!(last < data.len(), "a {rows}x{cols} view needs index {last}");
        }
        View {
            data,
            rows,
            cols,
            row_stride,
            col_stride,
        }
    }

    /// The transpose (no copy).
    pub fn t(self) -> Self {
        View {
            rows: self.cols,
            cols: self.rows,
            row_stride: self.col_stride,
            col_stride: self.row_stride,
            ..self
        }
    }
}

/// `out = a b` (or `out += a b` with `accumulate`), `out` row-major `a.rows x b.cols`.
pub fn matmul(a: View, b: View, out: &mut [f32], accumulate: bool) {
    let (m, k, n) = (a.rows, a.cols, b.cols);
    assert_eq!(k, b.rows, "inner sizes differ");
    assert_eq!(out.len(), m * n, "output is not {m}x{n}");
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            out.fill(0.0);
        }
        return;
    }
    if thin_product(a, b, out, accumulate) {
        return;
    }
    // SAFETY: the views' constructors checked that every element they address lies inside
    // their slices, `out` holds exactly m x n row-major elements, and `out` cannot alias the
    // inputs (it is borrowed mutably while they are borrowed shared).
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            out.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            a.data.as_ptr(),
            a.col_stride as isize,
            a.row_stride as isize,
            b.data.as_ptr(),
            b.col_stride as isize,
            b.row_stride as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// Results this narrow or narrower are computed as dot products.
const THIN: usize = 2;

/// Products with one side one or two rows or columns, which a blocked kernel spends mostly on
/// padding (a one-column result fills one lane of a 16-lane register): a matrix times one or
/// two vectors, a vector times a matrix, and an outer product. Returns false, having done nothing,
/// for any other shape or where the operands are not laid out for a contiguous inner loop.
fn thin_product(a: View, b: View, out: &mut [f32], accumulate: bool) -> bool {
    let (m, k, n) = (a.rows, a.cols, b.cols);
    if n <= THIN && a.col_stride == 1 && b.row_stride == 1 {
        // Matrix times a few vectors: one dot product per row and vector.
        let columns: Vec<&[f32]> = (0..n).map(|j| &b.data[j * b.col_stride..][..k]).collect();
        for (r, o) in out.chunks_exact_mut(n).enumerate() {
            let x = row(&a, r, k);
            for (o, y) in o.iter_mut().zip(&columns) {
                let d = dot(x, y);
                *o = if accumulate { *o + d } else { d };
            }
        }
        return true;
    }
    if m == 1 && a.col_stride == 1 && b.col_stride == 1 {
        // Vector times matrix: the matrix's rows summed with the vector's weights, in order.
        if !accumulate {
            out.fill(0.0);
        }
        for r in 0..k {
            let w = a.data[r];
            out.iter_mut()
                .zip(row(&b, r, n))
                .for_each(|(o, x)| *o += w * x);
        }
        return true;
    }
    if k == 1 && b.col_stride == 1 {
        // Outer product of a column and a row.
        let y = &b.data[..n];
        for (r, o) in out.chunks_exact_mut(n).enumerate() {
            let w = a.data[r * a.row_stride];
            if accumulate {
                o.iter_mut().zip(y).for_each(|(o, y)| *o += w * y);
            } else {
                o.iter_mut().zip(y).for_each(|(o, y)| *o = w * y);
            }
        }
        return true;
    }
    false
}

/// Row `r` of `v`, `len` elements (contiguous where `v.col_stride` is 1).
fn row<'a>(v: &View<'a>, r: usize, len: usize) -> &'a [f32] {
    &v.data[r * v.row_stride..][..len]
}

/// A dot product in eight interleaved partial sums (a fixed order, so the result does not
/// depend on the machine), which the compiler can keep in one vector register.
fn dot(x: &[f32], y: &[f32]) -> f32 {
    const LANES: usize = 8;
    let mut acc = [0.0f32; LANES];
    let (xc, yc) = (x.chunks_exact(LANES), y.chunks_exact(LANES));
    let (xr, yr) = (xc.remainder(), yc.remainder());
    for (xs, ys) in xc.zip(yc) {
        for l in 0..LANES {
            acc[l] += xs[l] * ys[l];
        }
    }
    let tail: f32 = xr.iter().zip(yr).map(|(a, b)| a * b).sum();
    acc.iter().sum::<f32>() + tail
}

#[cfg(test)]
mod tests {
    use super::*;

    fn naive(a: View, b: View) -> Vec<f32> {
        let at = |v: &View, r: usize, c: usize| v.data[r * v.row_stride + c * v.col_stride];
        let mut out = vec![0.0; a.rows * b.cols];
        for r in 0..a.rows {
            for c in 0..b.cols {
                out[r * b.cols + c] = (0..a.cols).map(|k| at(&a, r, k) * at(&b, k, c)).sum();
            }
        }
        out
    }

    #[test]
    fn products_of_views_match_the_definition() {
        let a: Vec<f32> = (0..35).map(|i| (i as f32 * 0.37).sin()).collect(); // 5 x 7
        let b: Vec<f32> = (0..28).map(|i| (i as f32 * 0.11).cos()).collect(); // 7 x 4
        let cases = [
            (View::new(&a, 5, 7), View::new(&b, 7, 4)),
            (View::new(&a, 7, 5).t(), View::new(&b, 4, 7).t()),
            (View::columns(&a, 5, 7, 2, 3), View::columns(&b, 3, 4, 1, 2)),
            // thin products: matrix x vector (17 > the dot product's 8 lanes), vector x
            // matrix, outer product, each also with operands laid out the other way
            (View::new(&a, 2, 17), View::new(&b, 17, 1)),
            (View::new(&a, 17, 2).t(), View::new(&b, 1, 17).t()),
            (View::new(&a, 2, 12), View::new(&b, 2, 12).t()),
            (View::new(&a, 1, 7), View::new(&b, 7, 4)),
            (View::new(&a, 7, 1).t(), View::new(&b, 4, 7).t()),
            (View::new(&a, 5, 1), View::new(&b, 1, 4)),
            (View::new(&a, 1, 5).t(), View::new(&b, 4, 1).t()),
        ];
        for (x, y) in cases {
            let want = naive(x, y);
            let mut out = vec![1.0; x.rows * y.cols];
            matmul(x, y, &mut out, false);
            for (o, w) in out.iter().zip(&want) {
                assert!((o - w).abs() < 1e-5, "{o} vs {w}");
            }
            matmul(x, y, &mut out, true);
            for (o, w) in out.iter().zip(&want) {
                assert!((o - 2.0 * w).abs() < 1e-5, "accumulated {o} vs {}", 2.0 * w);
            }
        }
    }

    #[test]
    #[should_panic(expected = "view needs index")]
    fn a_view_past_its_slice_is_refused() {
        View::new(&[0.0; 5], 2, 3);
    }
}
