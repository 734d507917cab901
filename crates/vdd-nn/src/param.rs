//! Parameters: flat `f32` tensors with their gradients, and the [`Parameters`] visitor that
//! optimisers, EMA and serialisation walk.

/// One tensor, stored flat in PyTorch's row-major layout (a `Linear` weight is `[out, in]`,
/// exactly as `torch.nn.Linear.weight`), with a gradient buffer of the same size.
///
/// Most parameters are trainable; a *buffer* ([`Param::buffer`], `trainable == false`) is a
/// fixed tensor that belongs to the model's state (saved and loaded with it, like PyTorch's
/// registered buffers or `requires_grad=False` parameters) but that optimisers, gradient
/// clipping and gradient checks leave alone.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Param {
    /// The values, row-major in `shape`.
    pub value: Vec<f32>,
    /// The accumulated gradient (same layout).
    #[serde(skip)]
    pub grad: Vec<f32>,
    /// The tensor's shape, PyTorch convention.
    pub shape: Vec<usize>,
    /// Whether optimisers update it (`false` for fixed buffers).
    #[serde(default = "yes")]
    pub trainable: bool,
}

fn yes() -> bool {
    true
}

impl Param {
    /// A parameter with the given values; panics if `value.len()` does not match `shape`
    /// (a programming error inside this crate, never user input).
    pub fn new(shape: &[usize], value: Vec<f32>) -> Self {
        let n: usize = shape.iter().product();
        assert_eq!(n, value.len(), "parameter size does not match its shape");
        Self { grad: vec![0.0; n], value, shape: shape.to_vec(), trainable: true }
    }

    /// A fixed, non-trainable tensor (see the type's documentation); panics if `value.len()`
    /// does not match `shape`.
    pub fn buffer(shape: &[usize], value: Vec<f32>) -> Self {
        Self { trainable: false, ..Self::new(shape, value) }
    }

    /// A zero-initialised parameter.
    pub fn zeros(shape: &[usize]) -> Self {
        let n: usize = shape.iter().product();
        Self::new(shape, vec![0.0; n])
    }

    /// Number of scalars.
    pub fn len(&self) -> usize {
        self.value.len()
    }

    /// Whether the parameter holds no scalars.
    pub fn is_empty(&self) -> bool {
        self.value.is_empty()
    }

    /// Sets the gradient to zero (re-allocating it if it was skipped by deserialisation).
    pub fn zero_grad(&mut self) {
        if self.grad.len() != self.value.len() {
            self.grad = vec![0.0; self.value.len()];
        } else {
            self.grad.fill(0.0);
        }
    }
}

/// Joins a parameter-name prefix and a local name PyTorch-style (`"layers.0" + "weight"`).
pub fn join_name(prefix: &str, name: &str) -> String {
    if prefix.is_empty() { name.to_owned() } else { format!("{prefix}.{name}") }
}

/// Anything that owns parameters: layers, networks, whole models made of several networks.
///
/// Names follow PyTorch's `state_dict` convention so a PyTorch model of the same architecture
/// maps one to one. Visiting order is fixed; optimisers rely on it.
pub trait Parameters {
    /// Calls `f(name, param)` for every parameter, names prefixed with `prefix`.
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param));

    /// Calls `f(name, param)` for every parameter, mutably.
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param));

    /// Zeroes every gradient.
    fn zero_grad(&mut self) {
        self.visit_params_mut("", &mut |_, p| p.zero_grad());
    }

    /// Total number of scalars (buffers included, as PyTorch's `numel` over `state_dict`).
    fn num_params(&self) -> usize {
        let mut n = 0;
        self.visit_params("", &mut |_, p| n += p.len());
        n
    }
}
