//! Tests of the VDD method: cache keys and the row settings that reach the student.

use super::*;
use crate::recipe;
use crate::tasks::AvoidingRecipe;

#[test]
fn a_selection_by_another_series_has_a_cache_key_of_its_own() {
    assert_eq!(selected_key("abc", DEFAULT_SELECTION).unwrap(), "abc");
    let other = selected_key("abc", "held-out success rate").unwrap();
    assert_ne!(other, "abc");
    assert_eq!(other, selected_key("abc", "held-out success rate").unwrap());
    assert_ne!(other, selected_key("abd", "held-out success rate").unwrap());
}

#[test]
fn a_uniform_students_key_ignores_the_gating_network_and_a_learned_ones_does_not() {
    let mut a = MoeConfig::toy(2, 2, 4);
    a.gating = GatingKind::Uniform;
    let mut b = a.clone();
    b.gating_network.hidden_dim += 32;
    assert_eq!(keyed_student(&a), keyed_student(&b));
    a.gating = GatingKind::Learned;
    b.gating = GatingKind::Learned;
    assert_ne!(keyed_student(&a), keyed_student(&b));
    let mut c = a.clone();
    c.experts_network.hidden_dim += 32;
    assert_ne!(keyed_student(&a), keyed_student(&c));
}

#[test]
fn a_rows_own_number_of_experts_reaches_its_student() {
    let file = recipe::read_recipe(&recipe::recipe_path("avoiding").unwrap()).unwrap();
    let sets = vec![("vdd.beso_experts".to_owned(), "4".to_owned())];
    let o = recipe::Overrides { sets, ..Default::default() };
    let r = recipe::resolve(&AvoidingRecipe::defaults().unwrap(), &file, &o).unwrap();
    let tree = recipe::to_tree(&r.base).unwrap();
    let registry = crate::Registry::builtin();
    let experts = |row: &str| {
        let row = registry.row(row).unwrap();
        let (teachers, student) = (&r.base.teachers, &r.base.student);
        let view = MethodRecipe { teachers, student, tree: &tree, row };
        Vdd.settings(&view).unwrap().student.num_experts
    };
    assert_eq!(experts("vdd-beso"), 4);
    assert_eq!(experts("vdd-ddpm"), 16);
}
