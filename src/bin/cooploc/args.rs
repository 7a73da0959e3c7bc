//! Argument types the commands share: methods and encodings as clap value enums (clap checks
//! them, lists them in `--help` and names the valid ones in its error), parsed once here.

use clap::ValueEnum;
use clap::builder::PossibleValue;
use cooploc::dataset::run::Regime;
use cooploc::estimation::Method;
use cooploc::protocol::record::Encoding;
use cooploc::sitl::scenario::{PAPER_TOML, Scenario};
use std::path::{Path, PathBuf};

/// Which simulated run: the scenario, and the seed, run and ranging schedule that pick its
/// sensor errors and ranges (as in `cooploc experiment`).
#[derive(clap::Args, Debug, Clone)]
pub struct SimRun {
    /// Scenario file (default: the paper's scenario, built in: sitl/scenarios/paper.toml).
    pub scenario: Option<PathBuf>,
    /// Seed of the sensor errors (as in `cooploc experiment`).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Monte Carlo run index (with the seed, picks the sensor errors).
    #[arg(long, default_value_t = 0)]
    pub run: u32,
    /// Ranging schedule of the scenario (default: its first).
    #[arg(long)]
    pub schedule: Option<String>,
}

/// Any method, by its short name (`dr`, `naive`, `dcl`, `centralized`, `ci`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MethodArg(pub Method);

impl ValueEnum for MethodArg {
    fn value_variants<'a>() -> &'a [Self] {
        const ALL: [MethodArg; 5] = [
            MethodArg(Method::DeadReckoning),
            MethodArg(Method::NoPropagation),
            MethodArg(Method::Decentralized),
            MethodArg(Method::Centralized),
            MethodArg(Method::CovarianceIntersection),
        ];
        &ALL
    }
    fn to_possible_value(&self) -> Option<PossibleValue> {
        Some(PossibleValue::new(self.0.short_name()))
    }
}

/// A method a node runs (every one but the centralized filter, which needs a central computer).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NodeMethodArg(pub Method);

impl ValueEnum for NodeMethodArg {
    fn value_variants<'a>() -> &'a [Self] {
        const NODE: [NodeMethodArg; 4] = [
            NodeMethodArg(Method::DeadReckoning),
            NodeMethodArg(Method::NoPropagation),
            NodeMethodArg(Method::Decentralized),
            NodeMethodArg(Method::CovarianceIntersection),
        ];
        &NODE
    }
    fn to_possible_value(&self) -> Option<PossibleValue> {
        Some(PossibleValue::new(self.0.short_name()))
    }
}

/// One method, or `all`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MethodsArg {
    One(Method),
    All,
}

impl MethodsArg {
    pub fn methods(self) -> Vec<Method> {
        match self {
            MethodsArg::One(m) => vec![m],
            MethodsArg::All => Method::ALL.to_vec(),
        }
    }
}

impl ValueEnum for MethodsArg {
    fn value_variants<'a>() -> &'a [Self] {
        const ALL: [MethodsArg; 6] = [
            MethodsArg::One(Method::DeadReckoning),
            MethodsArg::One(Method::NoPropagation),
            MethodsArg::One(Method::Decentralized),
            MethodsArg::One(Method::Centralized),
            MethodsArg::One(Method::CovarianceIntersection),
            MethodsArg::All,
        ];
        &ALL
    }
    fn to_possible_value(&self) -> Option<PossibleValue> {
        Some(PossibleValue::new(match self {
            MethodsArg::One(m) => m.short_name(),
            MethodsArg::All => "all",
        }))
    }
}

/// The methods of a list of [`MethodsArg`], each once, in the order given.
pub fn methods_of(list: &[MethodsArg]) -> Vec<Method> {
    let mut out = Vec::new();
    for m in list.iter().flat_map(|m| m.methods()) {
        if !out.contains(&m) {
            out.push(m);
        }
    }
    out
}

/// A data set regime (`no-landmarks`, `map-blind`, `full-map`), or `all`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RegimesArg {
    One(Regime),
    All,
}

impl ValueEnum for RegimesArg {
    fn value_variants<'a>() -> &'a [Self] {
        const ALL: [RegimesArg; 4] = [
            RegimesArg::One(Regime::NoLandmarks),
            RegimesArg::One(Regime::MapBlind),
            RegimesArg::One(Regime::FullMap),
            RegimesArg::All,
        ];
        &ALL
    }
    fn to_possible_value(&self) -> Option<PossibleValue> {
        Some(PossibleValue::new(match self {
            RegimesArg::One(r) => r.name(),
            RegimesArg::All => "all",
        }))
    }
}

/// The regimes of a list of [`RegimesArg`], each once, in their own order.
pub fn regimes_of(list: &[RegimesArg]) -> Vec<Regime> {
    Regime::ALL.into_iter().filter(|r| list.iter().any(|a| *a == RegimesArg::All || *a == RegimesArg::One(*r))).collect()
}

/// A record encoding (`f64`, `f32`, `compact`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EncodingArg(pub Encoding);

impl ValueEnum for EncodingArg {
    fn value_variants<'a>() -> &'a [Self] {
        const ALL: [EncodingArg; 3] = [EncodingArg(Encoding::F64), EncodingArg(Encoding::F32), EncodingArg(Encoding::Compact)];
        &ALL
    }
    fn to_possible_value(&self) -> Option<PossibleValue> {
        Some(PossibleValue::new(self.0.name()))
    }
}

/// One encoding, or `all`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EncodingsArg {
    One(Encoding),
    All,
}

impl EncodingsArg {
    pub fn encodings(self) -> Vec<Encoding> {
        match self {
            EncodingsArg::One(e) => vec![e],
            EncodingsArg::All => Encoding::ALL.to_vec(),
        }
    }
}

impl ValueEnum for EncodingsArg {
    fn value_variants<'a>() -> &'a [Self] {
        const ALL: [EncodingsArg; 4] = [
            EncodingsArg::One(Encoding::F64),
            EncodingsArg::One(Encoding::F32),
            EncodingsArg::One(Encoding::Compact),
            EncodingsArg::All,
        ];
        &ALL
    }
    fn to_possible_value(&self) -> Option<PossibleValue> {
        Some(PossibleValue::new(match self {
            EncodingsArg::One(e) => e.name(),
            EncodingsArg::All => "all",
        }))
    }
}

/// The scenario at `path`, or the paper's when none is given: built into the binary, so that a
/// command runs from any folder, not only from the repository.
pub fn scenario_or_paper(path: Option<&Path>) -> anyhow::Result<Scenario> {
    Ok(match path {
        Some(p) => Scenario::from_path(p)?,
        None => Scenario::from_toml_str(PAPER_TOML)?,
    })
}

/// `--reach-m`: the radios' reach replaces the scenario's (two vehicles range only while at
/// most this far apart); a reach that is not a positive distance is refused.
pub fn limit_reach(scenario: &mut Scenario, reach_m: Option<f64>) -> anyhow::Result<()> {
    if let Some(r) = reach_m {
        if !(r.is_finite() && r > 0.0) {
            anyhow::bail!("--reach-m {r}: the radios' reach must be a positive distance in m");
        }
        scenario.ranging.max_range_m = Some(r);
    }
    Ok(())
}

/// How the scenario of [`scenario_or_paper`] is named in a command's output.
pub fn scenario_source(path: Option<&Path>) -> String {
    path.map_or_else(|| "built in, as sitl/scenarios/paper.toml".to_string(), |p| p.display().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_value_enum_covers_the_library_lists() {
        assert_eq!(MethodArg::value_variants().iter().map(|m| m.0).collect::<Vec<_>>(), Method::ALL.to_vec());
        assert_eq!(MethodsArg::All.methods(), Method::ALL.to_vec());
        assert!(!NodeMethodArg::value_variants().iter().any(|m| m.0 == Method::Centralized));
        assert_eq!(EncodingArg::value_variants().iter().map(|e| e.0).collect::<Vec<_>>(), Encoding::ALL.to_vec());
        assert_eq!(MethodArg::from_str("dcl", false), Ok(MethodArg(Method::Decentralized)));
        assert!(NodeMethodArg::from_str("centralized", false).is_err());
        assert_eq!(EncodingsArg::from_str("all", false).map(EncodingsArg::encodings), Ok(Encoding::ALL.to_vec()));
        let dcl = MethodsArg::One(Method::Decentralized);
        let all_after_dcl = [
            Method::Decentralized,
            Method::DeadReckoning,
            Method::NoPropagation,
            Method::Centralized,
            Method::CovarianceIntersection,
        ];
        assert_eq!(methods_of(&[dcl, MethodsArg::All, dcl]), all_after_dcl, "each once, in the order given");
        assert_eq!(
            regimes_of(&[RegimesArg::One(Regime::FullMap), RegimesArg::One(Regime::NoLandmarks)]),
            vec![Regime::NoLandmarks, Regime::FullMap]
        );
        assert_eq!(regimes_of(&[RegimesArg::All]), Regime::ALL.to_vec());
    }
}
