//! Which records an epoch runs on, when the cooperative network may carry forgeries (an
//! unsigned network) or a member has lost itself: pure, and a function of the records alone, so
//! that every node that holds the same records refuses the same ones and the team stays in step.
//!
//! Two rules, in this order:
//!
//! 1. **Contradicted by the team's ranges.** A record is refused when most of the ranges that
//!    *other* members measured to its platform (in their own, uncontested records) are off by
//!    more than [`CONTRADICTION_NIS`] (a false alarm of 1e-9 per range) against the positions
//!    the records carry, with the largest variance the two covariances allow (the sum of the
//!    standard deviations along the line of sight, squared: the cross-covariance between two
//!    members is at most that). A forged state 100 m away, a genuine record relabelled to a
//!    later epoch after the vehicle moved, a member that restarted with a stale state: each is
//!    refused, and what the others measured is not gated away by it.
//! 2. **Rival records.** Two different records for the same platform and epoch that are both
//!    still standing: both are refused (nobody can tell which one its owner sent) and the
//!    platform is named, so a forger costs at most the epochs it touched.
//!
//! Only ranges measured by a member about another member count as evidence, and only from a
//! record without a rival (a forger cannot testify with a record it contests): a forged record
//! claiming ranges cannot make a genuine one refused unless it is the majority of the evidence.

use std::collections::BTreeMap;

use crate::estimation::{PlatformId, RangeSample};
use crate::protocol::record::StateRecord;

/// The squared, normalised range residual above which a range contradicts the positions of
/// the two records it joins: the chi-square(1) quantile at 1 - 1e-9.
pub const CONTRADICTION_NIS: f64 = 37.33;

/// What [`vet`] decided for one epoch.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Vetted {
    /// The records the epoch runs on, one per platform, ascending platform id.
    pub accepted: Vec<StateRecord>,
    /// The records refused because the team's ranges contradict them.
    pub contradicted: Vec<StateRecord>,
    /// Platforms with two different records or more still standing after rule 1: all refused.
    pub rivals: Vec<PlatformId>,
}

/// The residual of `r` against the positions of `from` and `to` as NIS (see the module docs).
/// `None` when a record has no position of the axes the range needs.
fn range_nis(r: &RangeSample, from: &StateRecord, to: &StateRecord) -> Option<f64> {
    let (a, b) = (&from.snapshot.geometry, &to.snapshot.geometry);
    let d = b.position_ned_m - a.position_ned_m;
    let dist = d.norm();
    if !dist.is_finite() || !r.range_m.is_finite() {
        return None;
    }
    let u = if dist > 1e-9 { d / dist } else { nalgebra::Vector3::new(1.0, 0.0, 0.0) };
    let sigma_along = |rec: &StateRecord| -> Option<f64> {
        let g = &rec.snapshot.geometry;
        let p = &rec.snapshot.covariance;
        let mut v = 0.0;
        for i in 0..3 {
            for j in 0..3 {
                if u[i] == 0.0 || u[j] == 0.0 {
                    continue;
                }
                let (Some(ii), Some(jj)) = (g.position_index[i], g.position_index[j]) else { continue };
                v += u[i] * u[j] * *p.get((ii, jj))?;
            }
        }
        Some(v.max(0.0).sqrt())
    };
    let s = (sigma_along(from)? + sigma_along(to)?).powi(2) + r.sigma_m.powi(2);
    if s <= 0.0 || !s.is_finite() {
        return None;
    }
    Some((r.range_m - dist).powi(2) / s)
}

/// Decides which of an epoch's candidate records run (see the module docs). `candidates` holds,
/// per platform, the distinct records received for the epoch (the node's own among them).
pub fn vet(candidates: BTreeMap<PlatformId, Vec<StateRecord>>) -> Vetted {
    let mut out = Vetted::default();
    // Evidence: ranges from uncontested records, measured by their owner about another member.
    let uncontested: BTreeMap<PlatformId, &StateRecord> =
        candidates.iter().filter(|(_, c)| c.len() == 1).map(|(&p, c)| (p, &c[0])).collect();
    let mut standing: BTreeMap<PlatformId, Vec<usize>> = BTreeMap::new();
    let mut refused: BTreeMap<PlatformId, Vec<usize>> = BTreeMap::new();
    for (&p, recs) in &candidates {
        for (i, rec) in recs.iter().enumerate() {
            let mut evidence = 0usize;
            let mut against = 0usize;
            for (&k, measurer) in &uncontested {
                if k == p {
                    continue;
                }
                for r in measurer.ranges.iter().filter(|r| r.from == k && r.to == p) {
                    if let Some(nis) = range_nis(r, measurer, rec) {
                        evidence += 1;
                        if nis > CONTRADICTION_NIS {
                            against += 1;
                        }
                    }
                }
            }
            if evidence > 0 && 2 * against > evidence {
                refused.entry(p).or_default().push(i);
            } else {
                standing.entry(p).or_default().push(i);
            }
        }
    }
    for (p, recs) in candidates {
        let (keep, no) = (standing.get(&p).map(Vec::as_slice).unwrap_or(&[]), refused.get(&p).map(Vec::as_slice).unwrap_or(&[]));
        if keep.len() > 1 {
            out.rivals.push(p);
        }
        for (i, r) in recs.into_iter().enumerate() {
            if no.contains(&i) {
                out.contradicted.push(r);
            } else if keep.len() == 1 {
                out.accepted.push(r);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::estimation::{Geometry, Snapshot, StoreRef};
    use crate::time::TimeUs;
    use nalgebra::{DMatrix, Vector3};

    fn record(id: PlatformId, at: [f64; 2], sigma_m: f64, ranges_to: &[(PlatformId, f64)]) -> StateRecord {
        StateRecord {
            snapshot: Snapshot {
                id,
                geometry: Geometry {
                    position_ned_m: Vector3::new(at[0], at[1], 0.0),
                    position_index: [Some(0), Some(1), None],
                    heading: None,
                },
                covariance: DMatrix::identity(3, 3) * sigma_m * sigma_m,
                psi: DMatrix::identity(3, 3),
            },
            digest: 7,
            own_ref: StoreRef::fresh(1),
            refs: Vec::new(),
            flags: 0,
            ranges: ranges_to
                .iter()
                .map(|&(to, range_m)| RangeSample { t: TimeUs(1_000_000), from: id, to, range_m, sigma_m: 0.1 })
                .collect(),
        }
    }

    /// Three members at (0,0), (30,0), (0,40), each ranging the two others truly.
    fn honest() -> Vec<StateRecord> {
        vec![
            record(1, [0.0, 0.0], 1.0, &[(2, 30.0), (3, 40.0)]),
            record(2, [30.0, 0.0], 1.0, &[(1, 30.0), (3, 50.0)]),
            record(3, [0.0, 40.0], 1.0, &[(1, 40.0), (2, 50.0)]),
        ]
    }

    fn candidates(recs: Vec<StateRecord>) -> BTreeMap<PlatformId, Vec<StateRecord>> {
        let mut m: BTreeMap<PlatformId, Vec<StateRecord>> = BTreeMap::new();
        for r in recs {
            m.entry(r.snapshot.id).or_default().push(r);
        }
        m
    }

    #[test]
    fn the_quantile_is_chi_square_one_at_one_in_a_billion() {
        use statrs::distribution::{ChiSquared, ContinuousCDF};
        let q = ChiSquared::new(1.0).unwrap().inverse_cdf(1.0 - 1e-9);
        assert!((q - CONTRADICTION_NIS).abs() < 0.01, "{q}");
    }

    #[test]
    fn an_honest_epoch_keeps_every_record() {
        let v = vet(candidates(honest()));
        assert_eq!(v.accepted, honest());
        assert!(v.contradicted.is_empty() && v.rivals.is_empty());
    }

    #[test]
    fn errors_within_the_covariances_are_not_contradictions() {
        // Member 2 is 5 m from where it says, with a 2 m sigma: 5 m / (1 + 2) m along the line
        // is 1.7 sigma. And a member of huge covariance is never contradicted.
        let mut recs = honest();
        recs[1] = record(2, [25.0, 0.0], 2.0, &[(1, 30.0), (3, 50.0)]);
        assert_eq!(vet(candidates(recs.clone())).accepted.len(), 3);
        recs[1] = record(2, [130.0, 0.0], 100.0, &[]);
        assert_eq!(vet(candidates(recs)).accepted.len(), 3);
    }

    #[test]
    fn a_record_far_from_where_the_teammates_range_it_is_refused_and_the_others_run() {
        let mut recs = honest();
        recs[1] = record(2, [130.0, 0.0], 0.1, &[]); // a forgery: 100 m off, confident, no ranges
        let v = vet(candidates(recs.clone()));
        assert_eq!(v.contradicted, vec![recs[1].clone()]);
        assert_eq!(v.accepted, vec![recs[0].clone(), recs[2].clone()]);
        assert!(v.rivals.is_empty());
    }

    #[test]
    fn a_forgery_beside_the_genuine_record_is_refused_and_the_genuine_one_runs() {
        let mut cands = candidates(honest());
        let forged = record(2, [130.0, 0.0], 0.1, &[(1, 130.0), (3, 136.0)]);
        cands.get_mut(&2).unwrap().insert(0, forged.clone()); // (whichever came first)
        let v = vet(cands);
        assert_eq!(v.contradicted, vec![forged]);
        assert_eq!(v.accepted, honest());
    }

    #[test]
    fn two_records_the_ranges_cannot_tell_apart_are_both_refused() {
        // A forgery 1 m from the genuine one: both fit the ranges; nobody can say which is the
        // owner's, so member 2 sits the epoch out (on every node alike).
        let mut cands = candidates(honest());
        cands.get_mut(&2).unwrap().push(record(2, [31.0, 0.0], 1.0, &[(1, 31.0), (3, 50.5)]));
        let v = vet(cands);
        assert_eq!(v.rivals, vec![2]);
        assert!(v.contradicted.is_empty());
        let h = honest();
        assert_eq!(v.accepted, vec![h[0].clone(), h[2].clone()]);
    }

    #[test]
    fn a_contested_record_cannot_testify_and_a_minority_of_lies_convicts_nobody() {
        // A forger contests member 3 with a record whose ranges put member 1 100 m off: as a
        // contested record it is no evidence. Member 2 (uncontested) still vouches for 1.
        let mut cands = candidates(honest());
        cands.get_mut(&3).unwrap().push(record(3, [0.0, 40.0], 1.0, &[(1, 140.0), (2, 150.0)]));
        let v = vet(cands);
        assert!(v.contradicted.is_empty(), "{v:?}");
        assert_eq!(v.rivals, vec![3]);
        // An uncontested liar among two honest witnesses: one range of two against member 1 is
        // not a majority.
        let mut recs = honest();
        recs[2] = record(3, [0.0, 40.0], 1.0, &[(1, 140.0), (2, 50.0)]);
        let v = vet(candidates(recs));
        assert_eq!(v.accepted.len(), 3, "{v:?}");
    }

    #[test]
    fn without_evidence_a_record_stands() {
        // Nobody ranged member 2: its record, wherever it says it is, is not contradicted.
        let recs = vec![
            record(1, [0.0, 0.0], 1.0, &[(3, 40.0)]),
            record(2, [500.0, 0.0], 0.1, &[]),
            record(3, [0.0, 40.0], 1.0, &[(1, 40.0)]),
        ];
        assert_eq!(vet(candidates(recs)).accepted.len(), 3);
    }
}
