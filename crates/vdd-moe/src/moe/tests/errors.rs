//! Bad configurations, shapes, non-finite inputs and normalisers are errors.

use super::*;

// ---------------------------------------------------------------------------------------
// Bad input.
// ---------------------------------------------------------------------------------------

fn is_shape(e: &MoeError) -> bool {
    matches!(e, MoeError::Core(CoreError::Shape { .. }))
}

#[test]
fn invalid_configurations_are_errors() {
    let base = config(2, 2, ExpertKind::Diagonal, GatingKind::Learned, true);
    let bad = [
        MoeConfig { state_dim: 0, ..base.clone() },
        MoeConfig { action_dim: 0, ..base.clone() },
        MoeConfig { num_experts: 0, ..base.clone() },
        MoeConfig { mean_bias_init: -1.0, ..base.clone() },
        MoeConfig { mean_bias_init: f32::NAN, ..base.clone() },
        MoeConfig { init_std: 1e-5, ..base.clone() },
        MoeConfig { init_std: f32::NAN, ..base.clone() },
        MoeConfig { min_std: -1.0, ..base.clone() },
        MoeConfig {
            experts_network: NetworkConfig { hidden_dim: 0, ..small_net() },
            ..base.clone()
        },
        MoeConfig {
            gating_network: NetworkConfig { hidden_dim: 0, ..small_net() },
            ..base.clone()
        },
    ];
    for cfg in bad {
        assert!(Moe::from_config(cfg.clone(), 0).is_err(), "{cfg:?}");
    }
    let family = DiagonalExpert::new(3, 1.0, 1e-4).unwrap();
    assert!(matches!(Moe::new(base, family, 0), Err(e) if is_shape(&e)));
}

#[test]
fn wrong_shapes_and_non_finite_inputs_are_errors() {
    let mut moe = built(config(2, 3, ExpertKind::Full, GatingKind::Learned, true), 16);
    let shape = |r: vdd_core::Result<()>| matches!(r, Err(CoreError::Shape { .. }));
    let nonfinite = |r: vdd_core::Result<()>| matches!(r, Err(CoreError::NonFinite { .. }));
    let mut a3 = [0.0f32; 3];

    // act / act_into
    assert!(matches!(moe.act(&[0.0]), Err(CoreError::Shape { .. })));
    assert!(shape(moe.act_into(&[0.0, 0.0], &mut [0.0; 2])));
    assert!(nonfinite(moe.act_into(&[f32::NAN, 0.0], &mut a3)));
    assert!(nonfinite(moe.act_into(&[f32::INFINITY, 0.0], &mut a3)));
    // act_batch
    let obs = obs_batch(4, 2);
    assert!(shape(moe.act_batch(obs_batch(4, 3).as_ref(), Mat::zeros(4, 3).as_mut())));
    assert!(shape(moe.act_batch(obs.as_ref(), Mat::zeros(3, 3).as_mut())));
    assert!(shape(moe.act_batch(obs.as_ref(), Mat::zeros(4, 2).as_mut())));
    let mut nan_obs = obs.clone();
    nan_obs[(2, 1)] = f32::NAN;
    assert!(nonfinite(moe.act_batch(nan_obs.as_ref(), Mat::zeros(4, 3).as_mut())));
    // log_likelihood
    let acts = Mat::<f32>::zeros(4, 3);
    let mut ll = vec![0.0; 4];
    assert!(shape(moe.log_likelihood(obs_batch(4, 1).as_ref(), acts.as_ref(), &mut ll)));
    assert!(shape(moe.log_likelihood(obs.as_ref(), Mat::zeros(4, 2).as_ref(), &mut ll)));
    assert!(shape(moe.log_likelihood(obs.as_ref(), Mat::zeros(3, 3).as_ref(), &mut ll)));
    assert!(shape(moe.log_likelihood(obs.as_ref(), acts.as_ref(), &mut [0.0; 3])));
    assert!(nonfinite(moe.log_likelihood(nan_obs.as_ref(), acts.as_ref(), &mut ll)));
    let mut nan_acts = acts.clone();
    nan_acts[(0, 2)] = f32::NEG_INFINITY;
    assert!(nonfinite(moe.log_likelihood(obs.as_ref(), nan_acts.as_ref(), &mut ll)));
    // An observation the normaliser maps out of f32 range (offset and scale at their bounds).
    let huge = faer::mat![[3e38f32, 0.0]];
    moe.set_normalizers(Some(Affine::new(vec![-1e6, 0.0], vec![1e-6, 1.0]).unwrap()), None)
        .unwrap();
    assert!(nonfinite(moe.act_batch(huge.as_ref(), Mat::zeros(1, 3).as_mut())));
    let one = Mat::<f32>::zeros(1, 3);
    assert!(nonfinite(moe.log_likelihood(huge.as_ref(), one.as_ref(), &mut [0.0])));

    // The trainer-facing API on normalised states.
    assert!(matches!(moe.forward(obs_batch(4, 3).as_ref()), Err(e) if is_shape(&e)));
    assert!(moe.forward_experts(nan_obs.as_ref()).is_err());
    assert!(moe.forward_gating(nan_obs.as_ref()).is_err());
    assert!(moe.expert_entropies(obs_batch(4, 1).as_ref()).is_err());
    let mut resp = Mat::<f32>::zeros(4, 3);
    assert!(moe.responsibilities(obs.as_ref(), acts.as_ref(), Mat::zeros(4, 2).as_mut()).is_err());
    assert!(moe.responsibilities(obs.as_ref(), nan_acts.as_ref(), resp.as_mut()).is_err());
    assert!(moe.responsibilities(nan_obs.as_ref(), acts.as_ref(), resp.as_mut()).is_err());
    assert!(moe.responsibilities(obs.as_ref(), acts.as_ref(), resp.as_mut()).is_ok());
}

#[test]
fn backward_passes_validate_their_gradients_and_need_a_forward() {
    let mut moe = built(config(2, 2, ExpertKind::Diagonal, GatingKind::Learned, false), 17);
    assert!(matches!(moe.backward_experts(&[]), Err(MoeError::NoForward(_))));
    assert!(matches!(
        moe.backward_gating(Mat::<f32>::zeros(0, 3).as_ref()),
        Err(MoeError::NoForward(_))
    ));
    moe.forward(obs_batch(4, 2).as_ref()).unwrap();
    let r = moe.expert().raw_dim();
    assert!(matches!(moe.backward_experts(&vec![0.0; 4 * 3 * r - 1]), Err(e) if is_shape(&e)));
    let mut g = vec![0.0; 4 * 3 * r];
    g[5] = f32::NAN;
    assert!(moe.backward_experts(&g).is_err());
    assert!(matches!(
        moe.backward_gating(Mat::<f32>::zeros(4, 2).as_ref()),
        Err(e) if is_shape(&e)
    ));
    assert!(moe.backward_gating(Mat::from_fn(4, 3, |_, _| f32::NAN).as_ref()).is_err());
    moe.backward_experts(&vec![0.0; 4 * 3 * r]).unwrap();
    moe.backward_gating(Mat::<f32>::zeros(4, 3).as_ref()).unwrap();
}

#[test]
fn invalid_normalizers_are_errors_and_change_nothing() {
    let mut moe = built(config(2, 3, ExpertKind::Diagonal, GatingKind::Uniform, true), 18);
    let before = (moe.normalizers().0.cloned(), moe.normalizers().1.cloned());
    let bad: [(Option<Affine>, Option<Affine>); 6] = [
        (Some(Affine::identity(3)), None),
        (None, Some(Affine::identity(2))),
        // Public fields allow what `Affine::new` rejects.
        (Some(Affine { offset: vec![0.0, 0.0], scale: vec![1.0] }), None),
        (None, Some(Affine { offset: vec![0.0; 3], scale: vec![1.0, -1.0, 1.0] })),
        (None, Some(Affine { offset: vec![0.0; 3], scale: vec![1.0, 0.0, 1.0] })),
        (Some(Affine { offset: vec![f32::NAN, 0.0], scale: vec![1.0; 2] }), None),
    ];
    for (o, a) in bad {
        assert!(moe.set_normalizers(o.clone(), a.clone()).is_err(), "{o:?} {a:?}");
        assert_eq!((moe.normalizers().0.cloned(), moe.normalizers().1.cloned()), before);
    }
    moe.set_normalizers(None, None).unwrap();
    assert_eq!(moe.normalizers(), (None, None));
}
