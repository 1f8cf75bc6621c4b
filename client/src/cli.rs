//! Arguments and helpers shared by the `cosurg` commands of this library (the command
//! enum and its dispatch live in the `cosurg-cli` package, beside `cosurg bench`).

use std::path::PathBuf;

use clap::Args;
use sim_core::SimOptions;
use sim_core::sim_fem::{LinearSolver, Model};

/// `--model`: sim-fem's [`Model`] under its own names (`linear`, `corotational`, `stvk`),
/// with `nonlinear` accepted as the former name of `stvk` (as in scene files).
pub fn model_parser() -> impl clap::builder::TypedValueParser<Value = Model> {
    use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};
    let help = |m: Model| match m {
        Model::Linear => "plain linear FEM (reference)",
        Model::Corotational => "co-rotational linear FEM (the product's model)",
        Model::StVK => "St Venant–Kirchhoff with Newton (non-linear reference)",
    };
    PossibleValuesParser::new(Model::ALL.map(|m| {
        let value = PossibleValue::new(m.name()).help(help(m));
        Model::ALIASES
            .iter()
            .filter(|(_, target)| *target == m)
            .fold(value, |value, (alias, _)| value.alias(alias))
    }))
    .try_map(|name| name.parse::<Model>())
}

/// Solver knobs shared by the simulation commands; unset ones come from the scene.
#[derive(Debug, Clone, Args, Default)]
pub struct SimKnobs {
    /// Deformation model.
    #[arg(long, value_parser = model_parser())]
    pub model: Option<Model>,
    /// Time step (s).
    #[arg(long)]
    pub dt: Option<f64>,
    /// CG iteration budget per step.
    #[arg(long)]
    pub cg_iterations: Option<usize>,
    /// Rotation-sharing angle tolerance θ_tol (degrees); 0 disables sharing.
    #[arg(long)]
    pub sharing_angle: Option<f64>,
    /// Switch the scene's tool-following refinement on or off.
    #[arg(long)]
    pub adaptivity: Option<bool>,
    /// Threads of the FEM step (default 1: the step stays on the simulation thread).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Linear solver of the implicit step: jacobi-pcg, mg-pcg, direct or auto (default: the
    /// scene's).
    #[arg(long)]
    pub solver: Option<LinearSolver>,
}

impl SimKnobs {
    pub fn apply(&self, o: &mut SimOptions) {
        if let Some(m) = self.model {
            o.step.model = m;
        }
        if let Some(dt) = self.dt {
            o.dt = dt;
        }
        if let Some(n) = self.cg_iterations {
            o.step.solver.max_iters = n;
        }
        if let Some(a) = self.adaptivity {
            o.adaptivity = a;
        }
        if let Some(a) = self.sharing_angle {
            o.sharing_angle_deg = (a > 0.0).then_some(a);
        }
        if let Some(t) = self.threads {
            o.step.threads = t.max(1);
        }
        if let Some(s) = self.solver {
            o.step.linear_solver = s;
        }
    }
}

/// Where a command writes its files: `--out DIR`, else `out/<command>-<timestamp>`.
pub fn out_dir(arg: &Option<PathBuf>, command: &str) -> PathBuf {
    arg.clone().unwrap_or_else(|| {
        let stamp = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_secs())
            .unwrap_or(0);
        PathBuf::from("out").join(format!("{command}-{stamp}"))
    })
}

/// Marker error: the coordinator refused us (exit code 3).
#[derive(Debug, thiserror::Error)]
#[error("refused by the coordinator: {0}")]
pub struct Refused(pub String);

pub fn exit_code(e: &anyhow::Error) -> i32 {
    if e.downcast_ref::<Refused>().is_some() {
        3
    } else {
        1
    }
}
