//! The graph builder: nodes and constants with unique names, and the mixture's layers as ONNX
//! operators (opset 17).

use vdd_nn::Activation;

use crate::proto::{self, Attr, Msg};

/// A graph under construction.
#[derive(Debug, Default)]
pub struct Graph {
    nodes: Vec<Msg>,
    initializers: Vec<Msg>,
    count: usize,
}

impl Graph {
    fn fresh(&mut self, hint: &str) -> String {
        self.count += 1;
        format!("{hint}_{}", self.count)
    }

    /// A node with one output (named after `hint`); returns the output's name.
    pub fn op(&mut self, op: &str, inputs: &[&str], attrs: &[(&str, Attr)]) -> String {
        let out = self.fresh(&op.to_lowercase());
        self.op_into(op, inputs, &out, attrs);
        out
    }

    /// A node writing the given output name.
    pub fn op_into(&mut self, op: &str, inputs: &[&str], out: &str, attrs: &[(&str, Attr)]) {
        let name = self.fresh(&format!("{op}_node"));
        self.nodes.push(proto::node(op, &name, inputs, &[out], attrs));
    }

    /// A float constant.
    pub fn f32s(&mut self, hint: &str, dims: &[usize], values: &[f32]) -> String {
        let name = self.fresh(hint);
        self.initializers.push(proto::f32_tensor(&name, dims, values));
        name
    }

    /// A float scalar.
    pub fn scalar(&mut self, v: f32) -> String {
        self.f32s("c", &[], &[v])
    }

    /// An int64 constant.
    pub fn i64s(&mut self, hint: &str, values: &[i64]) -> String {
        let name = self.fresh(hint);
        self.initializers.push(proto::i64_tensor(&name, &[values.len()], values));
        name
    }

    /// A bool constant.
    pub fn bools(&mut self, hint: &str, values: &[bool]) -> String {
        let name = self.fresh(hint);
        self.initializers.push(proto::bool_tensor(&name, &[values.len()], values));
        name
    }

    /// `x Wᵀ + b` for a PyTorch-layout weight `[out, in]` (row-major) and bias `[out]`.
    pub fn linear(&mut self, x: &str, weight: &[f32], bias: &[f32], in_dim: usize) -> String {
        let out_dim = bias.len();
        let mut wt = vec![0.0f32; in_dim * out_dim];
        for o in 0..out_dim {
            for i in 0..in_dim {
                wt[i * out_dim + o] = weight[o * in_dim + i];
            }
        }
        let w = self.f32s("weight_t", &[in_dim, out_dim], &wt);
        let b = self.f32s("bias", &[out_dim], bias);
        let y = self.op("MatMul", &[x, &w], &[]);
        self.op("Add", &[&y, &b], &[])
    }

    /// `softplus(x)` as `relu(x) + log(1 + exp(−|x|))` (no overflow for large `|x|`).
    pub fn softplus(&mut self, x: &str) -> String {
        let pos = self.op("Relu", &[x], &[]);
        let abs = self.op("Abs", &[x], &[]);
        let neg = self.op("Neg", &[&abs], &[]);
        let e = self.op("Exp", &[&neg], &[]);
        let one = self.scalar(1.0);
        let one_plus = self.op("Add", &[&e, &one], &[]);
        let log = self.op("Log", &[&one_plus], &[]);
        self.op("Add", &[&pos, &log], &[])
    }

    /// An activation, in the form `vdd_nn::Activation::apply` computes it.
    pub fn activation(&mut self, x: &str, act: Activation) -> String {
        match act {
            Activation::Identity => x.to_string(),
            Activation::Relu => self.op("Relu", &[x], &[]),
            Activation::Tanh => self.op("Tanh", &[x], &[]),
            Activation::Softplus => self.softplus(x),
            Activation::Silu => {
                let s = self.op("Sigmoid", &[x], &[]);
                self.op("Mul", &[x, &s], &[])
            }
            Activation::Gelu => {
                let c = self.scalar(std::f32::consts::FRAC_1_SQRT_2);
                let scaled = self.op("Mul", &[x, &c], &[]);
                let erf = self.op("Erf", &[&scaled], &[]);
                let one = self.scalar(1.0);
                let one_plus = self.op("Add", &[&erf, &one], &[]);
                let half = self.scalar(0.5);
                let hx = self.op("Mul", &[x, &half], &[]);
                self.op("Mul", &[&hx, &one_plus], &[])
            }
            Activation::Mish => {
                // x · tanh(softplus(x)) = x · n / (n + 2) with e = exp(clamp(x, −88, 20)),
                // n = e (e + 2): the form of `vdd_nn`'s Mish.
                let lo = self.scalar(-88.0);
                let hi = self.scalar(20.0);
                let clamped = self.op("Clip", &[x, &lo, &hi], &[]);
                let e = self.op("Exp", &[&clamped], &[]);
                let two = self.scalar(2.0);
                let e2 = self.op("Add", &[&e, &two], &[]);
                let n = self.op("Mul", &[&e, &e2], &[]);
                let n2 = self.op("Add", &[&n, &two], &[]);
                let t = self.op("Div", &[&n, &n2], &[]);
                self.op("Mul", &[x, &t], &[])
            }
        }
    }

    /// The `GraphProto` with these inputs and outputs.
    pub fn finish(self, name: &str, inputs: &[Msg], outputs: &[Msg]) -> Msg {
        let mut g = Msg::new();
        for n in &self.nodes {
            g = g.msg(1, n);
        }
        g = g.string(2, name);
        for t in &self.initializers {
            g = g.msg(5, t);
        }
        for i in inputs {
            g = g.msg(11, i);
        }
        for o in outputs {
            g = g.msg(12, o);
        }
        g
    }
}
