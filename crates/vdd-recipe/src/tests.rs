//! Tests of resolution, overlays, seed lists and hashes.

use serde::{Deserialize, Serialize};
use toml::{Table, Value};

use crate::*;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
enum Noise {
    Fixed { level: f32 },
    Uniform { min: f32, max: f32 },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Sched {
    Constant,
    LinearDecay { total_steps: u64 },
    Cosine { total_steps: u64, final_factor: f32 },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Inner {
    lr: f32,
    iterations: usize,
    noise: Noise,
    schedule: Sched,
    freeze: Option<usize>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct R {
    name: String,
    seeds: Vec<u64>,
    methods: Vec<String>,
    vdd: Inner,
}

fn defaults() -> R {
    R {
        name: "t".into(),
        seeds: vec![0],
        methods: vec!["vdd".into()],
        vdd: Inner {
            lr: 1e-3,
            iterations: 100,
            noise: Noise::Fixed { level: 0.1 },
            schedule: Sched::LinearDecay { total_steps: 100 },
            freeze: None,
        },
    }
}

fn table(s: &str) -> Table {
    s.parse().unwrap()
}

#[test]
fn file_quick_and_cli_overrides_apply_in_order() {
    let file = table(
        r#"
        name = "r"
        [vdd]
        lr = 5e-4
        [quick]
        "vdd.iterations" = 10
        "#,
    );
    let none = resolve(&defaults(), &file, &Overrides::default()).unwrap();
    assert_eq!(none.base.vdd.lr, 5e-4);
    assert_eq!(none.base.vdd.iterations, 100);
    assert_eq!(none.base.name, "r");
    let o = Overrides {
        quick: true,
        seeds: Some(vec![1, 2]),
        methods: Some(vec!["a".into(), "b".into()]),
        sets: vec![
            ("vdd.iterations".into(), "20".into()),
            ("vdd.freeze".into(), "7".into()),
            ("vdd.lr".into(), "2e-3".into()),
        ],
    };
    let r = resolve(&defaults(), &file, &o).unwrap();
    assert_eq!(r.base.vdd.iterations, 20, "--set wins over --quick");
    assert_eq!(r.base.vdd.freeze, Some(7), "optional keys can be set");
    assert_eq!(r.base.vdd.lr, 2e-3);
    assert_eq!(r.base.seeds, vec![1, 2]);
    assert_eq!(r.base.methods, vec!["a", "b"]);
    // Without --quick the quick table is ignored.
    let o2 = Overrides { quick: false, ..Default::default() };
    assert_eq!(resolve(&defaults(), &file, &o2).unwrap().base.vdd.iterations, 100);
}

#[test]
fn typos_and_bad_types_are_errors() {
    let bad_key = table("[vdd]\nlearning_rate = 1.0");
    let e = resolve(&defaults(), &bad_key, &Overrides::default()).unwrap_err().to_string();
    assert!(e.contains("vdd.learning_rate"), "{e}");
    let o = Overrides { sets: vec![("vdd.lrr".into(), "1".into())], ..Default::default() };
    let e = resolve(&defaults(), &Table::new(), &o).unwrap_err().to_string();
    assert!(e.contains("vdd.lrr"), "{e}");
    let o = Overrides { sets: vec![("vd.lr".into(), "1".into())], ..Default::default() };
    assert!(resolve(&defaults(), &Table::new(), &o).unwrap_err().to_string().contains("`vd`"));
    let o =
        Overrides { sets: vec![("vdd.iterations".into(), "many".into())], ..Default::default() };
    assert!(resolve(&defaults(), &Table::new(), &o).is_err());
    let top = table("nme = \"x\"");
    assert!(
        resolve(&defaults(), &top, &Overrides::default()).unwrap_err().to_string().contains("nme")
    );
}

#[test]
fn enum_tables_replace_instead_of_merging() {
    let file = table(
        r#"
        [vdd.noise]
        kind = "uniform"
        min = 0.05
        max = 0.2
        [vdd.schedule.cosine]
        total_steps = 5
        final_factor = 0.1
        "#,
    );
    let r = resolve(&defaults(), &file, &Overrides::default()).unwrap();
    assert_eq!(r.base.vdd.noise, Noise::Uniform { min: 0.05, max: 0.2 });
    assert_eq!(r.base.vdd.schedule, Sched::Cosine { total_steps: 5, final_factor: 0.1 });
    let o = Overrides {
        sets: vec![
            ("vdd.noise".into(), "{ kind = \"fixed\", level = 0.3 }".into()),
            ("vdd.schedule".into(), "constant".into()),
        ],
        ..Default::default()
    };
    let r = resolve(&defaults(), &Table::new(), &o).unwrap();
    assert_eq!(r.base.vdd.noise, Noise::Fixed { level: 0.3 });
    assert_eq!(r.base.vdd.schedule, Sched::Constant);
    // Partial updates of the same variant merge.
    let o =
        Overrides { sets: vec![("vdd.noise.level".into(), "0.2".into())], ..Default::default() };
    let r = resolve(&defaults(), &Table::new(), &o).unwrap();
    assert_eq!(r.base.vdd.noise, Noise::Fixed { level: 0.2 });
}

#[test]
fn variants_resolve_on_top_of_the_base() {
    let file = table(
        r#"
        [[variants]]
        name = "a"
        set = { "vdd.iterations" = 1 }
        [[variants]]
        name = "b"
        description = "two"
        set = { "vdd.iterations" = 2, "vdd.noise.level" = 0.5 }
        "#,
    );
    let o = Overrides { sets: vec![("vdd.lr".into(), "0.5".into())], ..Default::default() };
    let r = resolve(&defaults(), &file, &o).unwrap();
    let cs = r.configs();
    assert_eq!(cs.len(), 2);
    assert_eq!(cs[0].1.vdd.iterations, 1);
    assert_eq!(cs[1].1.vdd.iterations, 2);
    assert_eq!(cs[1].1.vdd.noise, Noise::Fixed { level: 0.5 });
    assert!(cs.iter().all(|(_, c)| c.vdd.lr == 0.5), "CLI overrides reach every variant");
    assert!(r.to_toml().unwrap().contains("[[variants]]"));
    let dup = table("[[variants]]\nname = \"a\"\n[[variants]]\nname = \"a\"");
    assert!(resolve(&defaults(), &dup, &Overrides::default()).is_err());
    let typo = table("[[variants]]\nname = \"a\"\nset = { \"vdd.nope\" = 1 }");
    assert!(
        resolve(&defaults(), &typo, &Overrides::default())
            .unwrap_err()
            .to_string()
            .contains("vdd.nope")
    );
}

#[test]
fn resolved_toml_round_trips_with_short_floats() {
    let r = resolve(&defaults(), &Table::new(), &Overrides::default()).unwrap();
    let text = r.to_toml().unwrap();
    assert!(text.contains("lr = 0.001"), "{text}");
    let again = resolve(&defaults(), &table(&text), &Overrides::default()).unwrap();
    assert_eq!(again.base, r.base);
}

#[test]
fn sibling_dotted_keys_and_new_optional_keys_merge() {
    let file = table(
        r#"
        [quick]
        "vdd.iterations" = 3
        "vdd.lr" = 0.5
        [vdd]
        freeze = 4
        "#,
    );
    let o = Overrides { quick: true, ..Default::default() };
    let r = resolve(&defaults(), &file, &o).unwrap();
    assert_eq!((r.base.vdd.iterations, r.base.vdd.lr, r.base.vdd.freeze), (3, 0.5, Some(4)));
    assert_eq!(r.base.vdd.noise, Noise::Fixed { level: 0.1 }, "untouched keys stay");
}

#[test]
fn values_parse_as_toml_or_strings() {
    assert_eq!(parse_value("3"), Value::Integer(3));
    assert_eq!(parse_value("1e-3"), Value::Float(1e-3));
    assert_eq!(parse_value("true"), Value::Boolean(true));
    assert_eq!(parse_value("heun"), Value::String("heun".into()));
    assert_eq!(parse_value("\"x y\""), Value::String("x y".into()));
    assert!(matches!(parse_value("[1, 2]"), Value::Array(a) if a.len() == 2));
}

#[test]
fn seed_lists_and_hashes() {
    assert_eq!(parse_seeds("0,1,2").unwrap(), vec![0, 1, 2]);
    assert_eq!(parse_seeds("2..5").unwrap(), vec![2, 3, 4]);
    assert!(parse_seeds("a").is_err());
    assert!(parse_seeds("3..3").is_err());
    assert!(parse_seeds("0..18446744073709551615").is_err());
    assert!(parse_seeds("0..1001").unwrap_err().to_string().contains("more than 1000"));
    assert_eq!(parse_seeds("0..1000").unwrap().len(), 1000);
    assert!(parse_seeds("9223372036854775808").unwrap_err().to_string().contains("too large"));
    assert!(parse_seeds(&vec!["1"; 1001].join(",")).is_err());
    let a = config_hash(&defaults()).unwrap();
    let mut d = defaults();
    d.vdd.lr = 2e-3;
    assert_ne!(a, config_hash(&d).unwrap());
    assert_eq!(a, config_hash(&defaults()).unwrap());
    assert_eq!(a.len(), 16);
}

/// The hashes key the teacher and student caches: these values were computed by the code
/// before it moved into this crate and must never change.
#[test]
fn config_hashes_are_pinned() {
    let json = serde_json::to_string(&defaults()).unwrap();
    assert_eq!(
        json,
        r#"{"name":"t","seeds":[0],"methods":["vdd"],"vdd":{"lr":0.001,"iterations":100,"noise":{"kind":"fixed","level":0.1},"schedule":{"linear_decay":{"total_steps":100}},"freeze":null}}"#
    );
    assert_eq!(config_hash(&defaults()).unwrap(), "39f6869d9563cca3");
    let mut d = defaults();
    d.vdd.freeze = Some(3);
    d.vdd.noise = Noise::Uniform { min: 0.05, max: 0.2 };
    d.vdd.schedule = Sched::Cosine { total_steps: 5, final_factor: 0.1 };
    assert_eq!(config_hash(&d).unwrap(), "413499c28ce5d1ef");
    assert_eq!(fnv1a(b"vdd"), 0x6915_2019_4edf_de09);
}

#[test]
fn values_are_read_at_dotted_paths_and_errors_name_the_path() {
    #[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
    struct Em {
        iterations: u32,
    }
    let tree: toml::Table =
        "[baselines.em]\niterations = 3\n[baselines.x]\nbad = 1\nn = 2".parse().unwrap();
    assert_eq!(get_path::<Em>(&tree, "baselines.em").unwrap(), Some(Em { iterations: 3 }));
    assert_eq!(get_path::<u32>(&tree, "baselines.em.iterations").unwrap(), Some(3));
    assert_eq!(get_path::<u32>(&tree, "baselines.imc.iterations").unwrap(), None);
    assert_eq!(get_path::<u32>(&tree, "baselines.em.iterations.deeper").unwrap(), None);
    let e = get_path::<Em>(&tree, "baselines.x").unwrap_err().to_string();
    assert!(e.starts_with("`baselines.x`: ") && e.contains("iterations"), "{e}");
    let e = get_path::<String>(&tree, "baselines.x.n").unwrap_err().to_string();
    assert!(e.starts_with("`baselines.x.n`: "), "{e}");
}
