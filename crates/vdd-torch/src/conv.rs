//! `torch.nn.Conv1d` and `torch.nn.ConvTranspose1d`, forward only, batched through one matrix
//! product each (im2col / col2im).
//!
//! Sequences are stored as `(batch · len) × channels` matrices: row `b · len + t` holds time
//! step `t` of sample `b`, column `c` channel `c` (PyTorch's `x[b, c, t]`). Each channel's
//! column is contiguous, so im2col copies contiguous runs and a skip connection's channel
//! concatenation is a column range.

use faer::{Accum, Mat, MatRef};
use vdd_nn::matmul;

use vdd_nn::{NnError, Param, Parameters, join_name};

/// Checks the sizes of a convolution `layer` and makes its zeroed weight (of `shape`) and
/// bias buffers.
fn conv_buffers(
    layer: &str,
    [in_ch, out_ch, kernel, stride]: [usize; 4],
    shape: [usize; 3],
) -> Result<(Param, Param), NnError> {
    if in_ch == 0 || out_ch == 0 || kernel == 0 || stride == 0 {
        return Err(NnError::Config(format!(
            "{layer} needs positive sizes, got in {in_ch}, out {out_ch}, kernel {kernel}, stride {stride}"
        )));
    }
    let weight = Param::buffer(&shape, vec![0.0; out_ch * in_ch * kernel]);
    Ok((weight, Param::buffer(&[out_ch], vec![0.0; out_ch])))
}

/// Resizes `m` to `rows × cols` when its shape differs (contents unspecified afterwards).
pub(crate) fn ensure(m: &mut Mat<f32>, rows: usize, cols: usize) {
    if m.nrows() != rows || m.ncols() != cols {
        *m = Mat::zeros(rows, cols);
    }
}

/// Column `j` of `x` as a contiguous slice, copied into `scratch` when its rows are strided.
pub(crate) fn column<'a>(x: MatRef<'a, f32>, j: usize, scratch: &'a mut Vec<f32>) -> &'a [f32] {
    match x.col(j).try_as_col_major() {
        Some(c) => c.as_slice(),
        None => {
            scratch.clear();
            scratch.extend(x.col(j).iter().copied());
            scratch
        }
    }
}

/// A 1-D convolution with PyTorch's parameters: `weight` `[out, in, kernel]`, `bias` `[out]`,
/// zero padding on both sides, a stride. Output length `(len + 2·padding − kernel)/stride + 1`.
///
/// ```
/// use vdd_torch::Conv1d;
/// let mut conv = Conv1d::new(2, 3, 3, 1, 1).unwrap();
/// conv.bias.value = vec![1.0, 2.0, 3.0];
/// let x = faer::Mat::<f32>::zeros(2 * 4, 2); // batch 2, length 4, 2 channels
/// let y = conv.forward(x.as_ref(), 2).unwrap();
/// assert_eq!((y.nrows(), y.ncols()), (8, 3));
/// assert_eq!(y[(5, 2)], 3.0);
/// ```
#[derive(Debug, Clone)]
pub struct Conv1d {
    /// `[out, in, kernel]`, row-major (PyTorch layout).
    pub weight: Param,
    /// `[out]`.
    pub bias: Param,
    in_ch: usize,
    out_ch: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
    cols: Mat<f32>,
    out: Mat<f32>,
    scratch: Vec<f32>,
}

impl Conv1d {
    /// A zero-initialised convolution (weights come from a checkpoint).
    pub fn new(
        in_ch: usize,
        out_ch: usize,
        kernel: usize,
        stride: usize,
        padding: usize,
    ) -> Result<Self, NnError> {
        let sizes = [in_ch, out_ch, kernel, stride];
        let (weight, bias) = conv_buffers("Conv1d", sizes, [out_ch, in_ch, kernel])?;
        Ok(Self {
            weight,
            bias,
            in_ch,
            out_ch,
            kernel,
            stride,
            padding,
            cols: Mat::new(),
            out: Mat::new(),
            scratch: Vec::new(),
        })
    }

    /// Output channels.
    pub fn out_channels(&self) -> usize {
        self.out_ch
    }

    /// The last output.
    pub(crate) fn output(&self) -> &Mat<f32> {
        &self.out
    }

    /// The last output, mutably.
    pub(crate) fn output_mut(&mut self) -> &mut Mat<f32> {
        &mut self.out
    }

    /// Output length for an input of length `len` (0 when the kernel does not fit).
    pub fn out_len(&self, len: usize) -> usize {
        let padded = len + 2 * self.padding;
        if padded < self.kernel { 0 } else { (padded - self.kernel) / self.stride + 1 }
    }

    /// Convolves `batch` sequences stored as `(batch · len) × in` (see the module docs) into
    /// `(batch · out_len) × out`.
    pub fn forward(
        &mut self,
        x: MatRef<'_, f32>,
        batch: usize,
    ) -> Result<MatRef<'_, f32>, NnError> {
        Ok(self.forward_mut(x, batch)?.as_ref())
    }

    /// [`Conv1d::forward`], the output buffer handed out mutably (for in-place layers after it).
    pub(crate) fn forward_mut(
        &mut self,
        x: MatRef<'_, f32>,
        batch: usize,
    ) -> Result<&mut Mat<f32>, NnError> {
        if batch == 0 || x.nrows() % batch != 0 || x.ncols() != self.in_ch {
            return Err(NnError::Config(format!(
                "Conv1d: input {}x{} is not (batch {batch} · len) x {}",
                x.nrows(),
                x.ncols(),
                self.in_ch
            )));
        }
        let len = x.nrows() / batch;
        let out_len = self.out_len(len);
        if out_len == 0 {
            return Err(NnError::Config(format!(
                "Conv1d: length {len} is shorter than the kernel"
            )));
        }
        let rows = batch * out_len;
        ensure(&mut self.out, rows, self.out_ch);
        for (j, &b) in self.bias.value.iter().enumerate() {
            self.out.col_as_slice_mut(j).fill(b);
        }
        // Weight `[out, in·kernel]` row-major is `(in·kernel) × out` column-major: the
        // transposed matrix the product needs, with column index `ci·kernel + k`.
        let k_in = self.in_ch * self.kernel;
        let wt = MatRef::from_column_major_slice(&self.weight.value, k_in, self.out_ch);
        if self.kernel == 1 && self.stride == 1 && self.padding == 0 {
            matmul(self.out.as_mut(), Accum::Add, x, wt, 1.0);
            return Ok(&mut self.out);
        }
        // im2col and product a chunk of whole samples at a time, so the columns stay in cache;
        // a weight too large for the cache is read once per chunk, so its chunks are made tall
        // enough for the product to reuse it.
        let mut per_chunk = IM2COL_FLOATS / (out_len * k_in);
        if k_in * self.out_ch > LARGE_WEIGHT_FLOATS {
            per_chunk = per_chunk.max(LARGE_WEIGHT_ROWS.div_ceil(out_len));
        }
        let per_chunk = per_chunk.clamp(1, batch);
        ensure(&mut self.cols, per_chunk * out_len, k_in);
        let (s, p) = (self.stride, self.padding as isize);
        for b0 in (0..batch).step_by(per_chunk) {
            let nb = per_chunk.min(batch - b0);
            let (xr, or, orows) = (b0 * len, b0 * out_len, nb * out_len);
            for ci in 0..self.in_ch {
                let src = &column(x, ci, &mut self.scratch)[xr..xr + nb * len];
                for k in 0..self.kernel {
                    let dst = &mut self.cols.col_as_slice_mut(ci * self.kernel + k)[..orows];
                    let shift = k as isize - p;
                    if s == 1 && out_len == len {
                        shifted_column(src, shift, len, dst);
                        continue;
                    }
                    // Outputs o with 0 ≤ o·s + shift < len read the input; the rest are zero.
                    let lo =
                        (if shift < 0 { shift.unsigned_abs().div_ceil(s) } else { 0 }).min(out_len);
                    let hi = (len as isize - shift).max(0) as usize;
                    let hi = hi.div_ceil(s).clamp(lo, out_len);
                    let start = ((lo * s) as isize + shift) as usize;
                    dst.fill(0.0);
                    for b in 0..nb {
                        let xs = &src[b * len + start.min(len)..(b + 1) * len];
                        let ds = &mut dst[b * out_len + lo..b * out_len + hi];
                        ds.iter_mut().zip(xs.iter().step_by(s)).for_each(|(d, &v)| *d = v);
                    }
                }
            }
            let out = self.out.as_mut().subrows_mut(or, orows);
            matmul(out, Accum::Add, self.cols.as_ref().subrows(0, orows), wt, 1.0);
        }
        Ok(&mut self.out)
    }
}

/// Floats of one chunk of [`Conv1d`]'s im2col columns.
const IM2COL_FLOATS: usize = 1 << 16;

/// A [`Conv1d`] weight of more floats than this (4 MiB, beyond a core's L2) is streamed from
/// memory by every chunk's product...
const LARGE_WEIGHT_FLOATS: usize = 1 << 20;

/// ... so its chunks hold at least this many output rows (LeRobot's default U-Net, 2048
/// channels at length 4, would otherwise read its 84 MB weight once per sample).
const LARGE_WEIGHT_ROWS: usize = 256;

/// One im2col column of a length-preserving stride-1 convolution: `dst[b·len + t] =
/// src[b·len + t + shift]` where `0 ≤ t + shift < len`, else zero; one copy of the whole column,
/// then each sample's `|shift|` boundary rows zeroed.
fn shifted_column(src: &[f32], shift: isize, len: usize, dst: &mut [f32]) {
    let rows = dst.len();
    let sh = shift.unsigned_abs().min(len);
    if shift >= 0 {
        dst[..rows - sh].copy_from_slice(&src[sh..rows]);
        dst[rows - sh..].fill(0.0);
    } else {
        dst[sh..].copy_from_slice(&src[..rows - sh]);
        dst[..sh].fill(0.0);
    }
    // Strided stores (a `fill` per sample would be a `memset` call per sample).
    let first = if shift >= 0 { len - sh } else { 0 };
    for t in first..first + sh {
        for v in dst[t..].iter_mut().step_by(len) {
            *v = 0.0;
        }
    }
}

impl Parameters for Conv1d {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        f(&join_name(prefix, "weight"), &self.weight);
        f(&join_name(prefix, "bias"), &self.bias);
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        f(&join_name(prefix, "weight"), &mut self.weight);
        f(&join_name(prefix, "bias"), &mut self.bias);
    }
}

/// A 1-D transposed convolution with PyTorch's parameters: `weight` `[in, out, kernel]`, `bias`
/// `[out]`; output length `(len − 1)·stride − 2·padding + kernel`. diffusion_policy's
/// `Upsample1d` is kernel 4, stride 2, padding 1 (doubling the length).
///
/// ```
/// use vdd_torch::ConvTranspose1d;
/// let mut up = ConvTranspose1d::new(1, 1, 4, 2, 1).unwrap();
/// up.weight.value = vec![1.0, 1.0, 1.0, 1.0];
/// let x = faer::Mat::from_fn(2, 1, |i, _| (i + 1) as f32); // batch 1, length 2
/// let y = up.forward(x.as_ref(), 1).unwrap();
/// let got: Vec<f32> = (0..4).map(|i| y[(i, 0)]).collect();
/// assert_eq!(got, [1.0, 3.0, 3.0, 2.0]);
/// ```
#[derive(Debug, Clone)]
pub struct ConvTranspose1d {
    /// `[in, out, kernel]`, row-major (PyTorch layout).
    pub weight: Param,
    /// `[out]`.
    pub bias: Param,
    in_ch: usize,
    out_ch: usize,
    kernel: usize,
    stride: usize,
    padding: usize,
    z: Mat<f32>,
    out: Mat<f32>,
}

impl ConvTranspose1d {
    /// A zero-initialised transposed convolution (weights come from a checkpoint).
    pub fn new(
        in_ch: usize,
        out_ch: usize,
        kernel: usize,
        stride: usize,
        padding: usize,
    ) -> Result<Self, NnError> {
        let sizes = [in_ch, out_ch, kernel, stride];
        let (weight, bias) = conv_buffers("ConvTranspose1d", sizes, [in_ch, out_ch, kernel])?;
        Ok(Self {
            weight,
            bias,
            in_ch,
            out_ch,
            kernel,
            stride,
            padding,
            z: Mat::new(),
            out: Mat::new(),
        })
    }

    /// Output length for an input of length `len` (0 when padding eats everything).
    pub fn out_len(&self, len: usize) -> usize {
        ((len.max(1) - 1) * self.stride + self.kernel).saturating_sub(2 * self.padding)
    }

    /// Transposed-convolves `batch` sequences `(batch · len) × in` into
    /// `(batch · out_len) × out`.
    pub fn forward(
        &mut self,
        x: MatRef<'_, f32>,
        batch: usize,
    ) -> Result<MatRef<'_, f32>, NnError> {
        if batch == 0 || x.nrows() % batch != 0 || x.ncols() != self.in_ch || x.nrows() == 0 {
            return Err(NnError::Config(format!(
                "ConvTranspose1d: input {}x{} is not (batch {batch} · len) x {}",
                x.nrows(),
                x.ncols(),
                self.in_ch
            )));
        }
        let len = x.nrows() / batch;
        let out_len = self.out_len(len);
        if out_len == 0 {
            return Err(NnError::Config("ConvTranspose1d: empty output".into()));
        }
        // z[(b, i), co·kernel + k] = Σ_ci x[(b, i), ci] w[ci, co, k]: the weight `[in, out·kernel]`
        // row-major is the right-hand side as it stands.
        let ok = self.out_ch * self.kernel;
        ensure(&mut self.z, x.nrows(), ok);
        let w = MatRef::from_row_major_slice(&self.weight.value, self.in_ch, ok);
        matmul(self.z.as_mut(), Accum::Replace, x, w, 1.0);
        ensure(&mut self.out, batch * out_len, self.out_ch);
        let (s, p) = (self.stride as isize, self.padding as isize);
        for co in 0..self.out_ch {
            let dst = self.out.col_as_slice_mut(co);
            dst.fill(self.bias.value[co]);
            for k in 0..self.kernel {
                let zs = self.z.col_as_slice(co * self.kernel + k);
                for b in 0..batch {
                    let ds = &mut dst[b * out_len..(b + 1) * out_len];
                    let src = &zs[b * len..(b + 1) * len];
                    for (i, &v) in src.iter().enumerate() {
                        let o = i as isize * s - p + k as isize;
                        if o >= 0 && (o as usize) < out_len {
                            ds[o as usize] += v;
                        }
                    }
                }
            }
        }
        Ok(self.out.as_ref())
    }
}

impl Parameters for ConvTranspose1d {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        f(&join_name(prefix, "weight"), &self.weight);
        f(&join_name(prefix, "bias"), &self.bias);
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        f(&join_name(prefix, "weight"), &mut self.weight);
        f(&join_name(prefix, "bias"), &mut self.bias);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Direct definition of PyTorch's Conv1d on one sample.
    fn naive_conv(c: &Conv1d, x: &[Vec<f32>], len: usize) -> Vec<Vec<f32>> {
        let ol = c.out_len(len);
        (0..c.out_ch)
            .map(|co| {
                (0..ol)
                    .map(|o| {
                        let mut acc = c.bias.value[co];
                        for ci in 0..c.in_ch {
                            for k in 0..c.kernel {
                                let t = (o * c.stride + k) as isize - c.padding as isize;
                                if t >= 0 && (t as usize) < len {
                                    acc += c.weight.value[(co * c.in_ch + ci) * c.kernel + k]
                                        * x[ci][t as usize];
                                }
                            }
                        }
                        acc
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn conv_matches_the_definition_for_strides_and_paddings() {
        for &(k, s, p) in &[(3, 1, 1), (3, 2, 1), (5, 1, 2), (1, 1, 0), (4, 2, 0)] {
            let mut c = Conv1d::new(3, 2, k, s, p).unwrap();
            for (i, w) in c.weight.value.iter_mut().enumerate() {
                *w = ((i * 7 % 11) as f32 - 5.0) * 0.1;
            }
            c.bias.value = vec![0.3, -0.2];
            let (batch, len) = (2, 8);
            let x = Mat::from_fn(batch * len, 3, |r, ch| ((r * 3 + ch * 5) % 7) as f32 - 3.0);
            let ol = c.out_len(len);
            let y = c.forward(x.as_ref(), batch).unwrap().to_owned();
            for b in 0..batch {
                let xs: Vec<Vec<f32>> =
                    (0..3).map(|ch| (0..len).map(|t| x[(b * len + t, ch)]).collect()).collect();
                let want = naive_conv(&c, &xs, len);
                for co in 0..2 {
                    for o in 0..ol {
                        assert!((y[(b * ol + o, co)] - want[co][o]).abs() < 1e-5, "k{k} s{s} p{p}");
                    }
                }
            }
        }
    }

    #[test]
    fn a_conv_with_a_large_weight_matches_the_definition_in_any_batch() {
        // 512 → 512 channels, kernel 5: a weight past `LARGE_WEIGHT_FLOATS`, so its chunks are
        // made tall; the samples must still come out as one at a time.
        let (cin, cout, k) = (512, 512, 5);
        assert!(cin * cout * k > LARGE_WEIGHT_FLOATS);
        let mut c = Conv1d::new(cin, cout, k, 1, 2).unwrap();
        for (i, w) in c.weight.value.iter_mut().enumerate() {
            *w = ((i * 7 % 11) as f32 - 5.0) * 0.01;
        }
        c.bias.value = (0..cout).map(|i| (i % 3) as f32 * 0.1).collect();
        let (batch, len) = (70, 4);
        let x = Mat::from_fn(batch * len, cin, |r, ch| ((r * 3 + ch * 5) % 7) as f32 - 3.0);
        let y = c.forward(x.as_ref(), batch).unwrap().to_owned();
        for b in [0, 33, 69] {
            let xs: Vec<Vec<f32>> =
                (0..cin).map(|ch| (0..len).map(|t| x[(b * len + t, ch)]).collect()).collect();
            let want = naive_conv(&c, &xs, len);
            for (co, w) in want.iter().enumerate() {
                for (o, &v) in w.iter().enumerate() {
                    let got = y[(b * len + o, co)];
                    assert!((got - v).abs() < 1e-3 * (1.0 + v.abs()), "{b} {co} {o}: {got} {v}");
                }
            }
        }
    }

    #[test]
    fn transposed_conv_is_the_adjoint_of_the_strided_conv() {
        // <conv(x), y> = <x, convT(y)> without biases, same weight tensor read as [out,in,k]
        // and [in,out,k] respectively.
        let (cin, cout, k, s, p) = (3, 2, 4, 2, 1);
        let mut c = Conv1d::new(cin, cout, k, s, p).unwrap();
        let mut t = ConvTranspose1d::new(cout, cin, k, s, p).unwrap();
        for (i, w) in c.weight.value.iter_mut().enumerate() {
            *w = ((i * 5 % 13) as f32 - 6.0) * 0.1;
        }
        t.weight.value.clone_from(&c.weight.value);
        let len = 8;
        let x = Mat::from_fn(len, cin, |r, ch| ((r + 2 * ch) % 5) as f32 - 2.0);
        let y = Mat::from_fn(c.out_len(len), cout, |r, ch| ((3 * r + ch) % 4) as f32 - 1.5);
        assert_eq!(t.out_len(y.nrows()), len);
        let cx = c.forward(x.as_ref(), 1).unwrap().to_owned();
        let ty = t.forward(y.as_ref(), 1).unwrap().to_owned();
        let lhs: f32 = (0..cx.nrows())
            .flat_map(|i| (0..cout).map(move |j| (i, j)))
            .map(|(i, j)| cx[(i, j)] * y[(i, j)])
            .sum();
        let rhs: f32 = (0..len)
            .flat_map(|i| (0..cin).map(move |j| (i, j)))
            .map(|(i, j)| x[(i, j)] * ty[(i, j)])
            .sum();
        assert!((lhs - rhs).abs() < 1e-4, "{lhs} vs {rhs}");
    }

    #[test]
    fn bad_shapes_are_errors() {
        let mut c = Conv1d::new(2, 2, 3, 1, 0).unwrap();
        assert!(c.forward(Mat::zeros(4, 3).as_ref(), 2).is_err());
        assert!(c.forward(Mat::zeros(2, 2).as_ref(), 1).is_err());
        assert!(Conv1d::new(0, 2, 3, 1, 0).is_err());
    }
}
