//! `vdd-oracle`, a diagnostic method (row `vdd-beso-oracle`): VDD's student from the row's
//! teacher (the same training as the `vdd` row, so the cached student when there is one)
//! acting with its gating replaced by the responsibilities of a teacher sample at each step
//! ([`OracleGating`]). Beside `vdd-beso` it tells whether the experts or the weights lose
//! success: if the oracle reaches the teacher's success, the experts hold the teacher's good
//! actions and only the weights are wrong. Its keys are VDD's.

use faer::MatRef;
use vdd_core::Policy;
use vdd_diffusion::DiffusionTeacher;
use vdd_moe::Moe;

use super::vdd::Vdd;
use crate::method::{Capability, Info, Job, Method, MethodRecipe, Row, TeacherUse, Trained};
use crate::policy::TrainedPolicy;

/// VDD's student with an oracle gating.
pub struct VddOracle;

const INFO: Info = Info {
    name: "vdd-oracle",
    teacher: TeacherUse::Learned,
    needs: &[Capability::Rollouts],
    row_keys: &[],
};

impl Method for VddOracle {
    fn info(&self) -> &Info {
        &INFO
    }
    fn keys(&self, row: &Row) -> Vec<String> {
        Vdd.keys(row)
    }
    fn shadowed_keys(&self, row: &Row) -> Vec<(String, Option<String>)> {
        Vdd.shadowed_keys(row)
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result {
        Vdd.check(recipe)
    }
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        let mut trained = Vdd.train(job)?;
        let TrainedPolicy::Moe(student) = trained.policy else {
            return Err("VDD did not train a mixture".into());
        };
        let teacher = job.teacher()?.teacher.clone();
        trained.policy = TrainedPolicy::Other(Box::new(OracleGating::new(*student, teacher)?));
        Ok(trained)
    }
}

/// A diagnostic policy (issue 33, "diagnostics first"): a mixture's experts with the gating
/// replaced, at every step, by the responsibilities of one of its teacher's samples. At the
/// observation `s` it draws `a_T` from the teacher, picks `z ~ q(z|a_T, s) ∝ q(z|s) N(a_T;
/// μ_z, Σ_z)` and acts `μ_z`. Its success against the mixture's own tells wrong weights (the
/// oracle does much better) from wrong experts (it does not). It costs a teacher sample per
/// action and allocates per call; it is for measuring, not for deployment.
#[derive(Debug, Clone)]
pub struct OracleGating<T = DiffusionTeacher> {
    student: Moe,
    teacher: T,
    rng: vdd_core::Rng,
    sample: Vec<f32>,
    log_resp: Vec<f32>,
    last: Vec<usize>,
}

impl<T: Policy> OracleGating<T> {
    /// `student`'s experts picked by the responsibilities of `teacher`'s samples; both act on
    /// the same raw observations.
    pub fn new(student: Moe, teacher: T) -> vdd_core::Result<Self> {
        let (d, z) = (Policy::action_dim(&student), student.num_experts());
        vdd_core::check_len("teacher actions", Policy::action_dim(&teacher), d)?;
        vdd_core::check_len("teacher observations", Policy::obs_dim(&teacher), student.obs_dim())?;
        Ok(Self {
            student,
            teacher,
            rng: vdd_core::Seeds::new(0).stream("oracle-gating"),
            sample: vec![0.0; d],
            log_resp: vec![0.0; z],
            last: vec![0],
        })
    }
}

impl<T: Policy> Policy for OracleGating<T> {
    fn obs_dim(&self) -> usize {
        self.student.obs_dim()
    }
    fn action_dim(&self) -> usize {
        Policy::action_dim(&self.student)
    }
    fn reset(&mut self) {
        self.student.reset();
        self.teacher.reset();
    }
    fn seed(&mut self, seed: u64) {
        self.teacher.seed(seed);
        self.rng = vdd_core::Seeds::new(seed).stream("oracle-gating");
    }
    fn last_experts(&self) -> &[usize] {
        &self.last
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        vdd_core::check_act_args(self, obs, action)?;
        self.teacher.act_into(obs, &mut self.sample)?;
        let c = self
            .student
            .components(MatRef::from_row_major_slice(obs, 1, obs.len()))
            .map_err(|e| vdd_core::CoreError::Config(e.to_string()))?;
        let d = c.action_dim;
        let mut work = vec![0.0; d];
        for (z, lr) in self.log_resp.iter_mut().enumerate() {
            let (mean, l) =
                (&c.means[z * d..(z + 1) * d], &c.scale_tril[z * d * d..(z + 1) * d * d]);
            *lr =
                c.log_gating[z] + vdd_core::gaussian::log_density(&self.sample, mean, l, &mut work);
        }
        vdd_core::gaussian::softmax_probs_in_place(&mut self.log_resp);
        let u: f32 = rand::Rng::random(&mut self.rng);
        let mut z = self.log_resp.len() - 1;
        let mut acc = 0.0;
        for (k, p) in self.log_resp.iter().enumerate() {
            acc += p;
            if u < acc {
                z = k;
                break;
            }
        }
        action.copy_from_slice(&c.means[z * d..(z + 1) * d]);
        self.last[0] = z;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vdd_moe::MoeConfig;

    /// A "teacher" that always acts `a`.
    #[derive(Debug, Clone)]
    struct Constant(Vec<f32>);

    impl Policy for Constant {
        fn obs_dim(&self) -> usize {
            1
        }
        fn action_dim(&self) -> usize {
            self.0.len()
        }
        fn act_into(&mut self, _obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
            action.copy_from_slice(&self.0);
            Ok(())
        }
    }

    #[test]
    fn the_oracle_picks_experts_by_the_responsibilities_of_the_teachers_sample() {
        let moe = Moe::from_config(MoeConfig::toy(1, 1, 4), 3).unwrap();
        let c = moe.clone().components(faer::mat![[0.2f32]].as_ref()).unwrap();
        let sample = c.means[2] + 0.3;
        // q(z|a, s) ∝ q(z|s) N(a; μ_z, σ_z²), computed here by hand.
        let joint: Vec<f64> = (0..4)
            .map(|z| {
                let (m, s) = (f64::from(c.means[z]), f64::from(c.scale_tril[z]));
                let g = f64::from(c.log_gating[z]).exp();
                g * (-0.5 * ((f64::from(sample) - m) / s).powi(2)).exp() / s
            })
            .collect();
        let total: f64 = joint.iter().sum();
        let mut oracle = OracleGating::new(moe, Constant(vec![sample])).unwrap();
        oracle.seed(7);
        let mut counts = [0usize; 4];
        for _ in 0..4000 {
            let a = oracle.act(&[0.2]).unwrap();
            let z = oracle.last_experts()[0];
            assert_eq!(a[0], c.means[z], "acts the picked expert's mean");
            counts[z] += 1;
        }
        for z in 0..4 {
            let (seen, expected) = (counts[z] as f64 / 4000.0, joint[z] / total);
            assert!((seen - expected).abs() < 0.03, "expert {z}: {seen} vs {expected}");
        }
    }
}
