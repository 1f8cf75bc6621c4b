//! The constitutive model: one enum for every crate (scene files, the FEM, the command
//! line), named `linear`, `corotational` and `stvk` everywhere; `nonlinear` is accepted as
//! an older name of `stvk`.

use std::fmt;
use std::str::FromStr;

/// Constitutive model.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Model {
    /// Small-strain linear elasticity `f = −K (x − X)` (reference; volume grows under
    /// rotation).
    Linear,
    /// Co-rotational linear: `f_e = −R_e K_e (R_eᵀ x_e − X_e)`, tangent `R K Rᵀ` with R
    /// frozen during a step (as SOFA). The product's model.
    #[default]
    Corotational,
    /// St Venant–Kirchhoff: `ψ = μ E:E + λ/2 tr²E`, `E = ½(FᵀF − I)`, consistent tangent,
    /// backward Euler with Newton (the non-linear reference). Also read as `nonlinear`.
    #[serde(alias = "nonlinear")]
    StVK,
}

/// A model name that is none of [`Model::NAMES`] (nor the alias `nonlinear`).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "unknown model `{0}`: expected one of `linear`, `corotational`, `stvk` (alias `nonlinear`)"
)]
pub struct UnknownModel(pub String);

impl Model {
    /// Every model, in the order of [`Model::NAMES`].
    pub const ALL: [Model; 3] = [Model::Linear, Model::Corotational, Model::StVK];
    /// The models' names as scene files, the command line and reports spell them.
    pub const NAMES: [&'static str; 3] = ["linear", "corotational", "stvk"];
    /// Older names still accepted: `(alias, model)`.
    pub const ALIASES: [(&'static str, Model); 1] = [("nonlinear", Model::StVK)];

    /// The model's name (`linear`, `corotational`, `stvk`).
    pub fn name(self) -> &'static str {
        match self {
            Model::Linear => "linear",
            Model::Corotational => "corotational",
            Model::StVK => "stvk",
        }
    }
}

impl fmt::Display for Model {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Model {
    type Err = UnknownModel;

    /// Parses a name of [`Model::NAMES`] or an alias of [`Model::ALIASES`] (exact,
    /// lowercase).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Model::ALL
            .into_iter()
            .find(|m| m.name() == s)
            .or_else(|| {
                Model::ALIASES
                    .iter()
                    .find(|(alias, _)| *alias == s)
                    .map(|(_, m)| *m)
            })
            .ok_or_else(|| UnknownModel(s.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_parse_back_and_nonlinear_is_stvk() {
        for (m, name) in Model::ALL.into_iter().zip(Model::NAMES) {
            assert_eq!(m.name(), name);
            assert_eq!(name.parse::<Model>().unwrap(), m);
            assert_eq!(m.to_string(), name);
        }
        assert_eq!("nonlinear".parse::<Model>().unwrap(), Model::StVK);
        let err = "StVK".parse::<Model>().unwrap_err();
        assert!(err.to_string().contains("unknown model `StVK`"), "{err}");
    }
}
