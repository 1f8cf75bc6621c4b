//! Region ownership arbitration (coordinator side).
//!
//! A region has at most one owner, the site whose simulation is authoritative for it and
//! which sends its keyframes. Sites request a region when their tool touches it.
//!
//! Precedence when a region is contested:
//! 1. an **instructor** beats a trainee (the instructor takes over even an established claim);
//! 2. otherwise the **earlier claim** wins. A request carries the time the site first touched
//!    the region (coordinator clock). The holder keeps the region unless the newcomer's claim
//!    is strictly earlier (ties: lower site id) *and* the holder was granted less than
//!    `contest_window_us` ago — i.e. the two requests crossed in flight. Claim times are
//!    clamped to `[now − window, now]`, so a site cannot gain precedence by lying about the past.
//! 3. observers never own regions.
//!
//! Outcomes are returned as [`OwnershipOutcome`]s: grants and releases are broadcast to all
//! sites (a grant names the previous owner that lost the region), denials go to the requester.

use std::collections::BTreeMap;

use crate::msg::{
    DenyReason, Message, OwnershipDeny, OwnershipGrant, OwnershipRelease, OwnershipRequest,
    RegionId, RegionOwner, Role, SiteId,
};

/// Default contest window: 100 ms.
pub const DEFAULT_CONTEST_WINDOW_US: u64 = 100_000;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Claim {
    site: SiteId,
    role: Role,
    claim_time_us: u64,
    granted_at_us: u64,
}

/// Result of an ownership operation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OwnershipOutcome {
    /// Broadcast to all sites.
    Grant(OwnershipGrant),
    /// Send to `to` only.
    Deny { to: SiteId, deny: OwnershipDeny },
    /// Broadcast to all sites.
    Release(OwnershipRelease),
}

impl OwnershipOutcome {
    /// The wire message.
    pub fn message(&self) -> Message {
        match *self {
            OwnershipOutcome::Grant(g) => Message::OwnershipGrant(g),
            OwnershipOutcome::Deny { deny, .. } => Message::OwnershipDeny(deny),
            OwnershipOutcome::Release(r) => Message::OwnershipRelease(r),
        }
    }

    /// `None` for broadcasts, `Some(site)` for a message to one site.
    pub fn recipient(&self) -> Option<SiteId> {
        match *self {
            OwnershipOutcome::Deny { to, .. } => Some(to),
            _ => None,
        }
    }
}

/// Owners of regions.
#[derive(Debug, Clone)]
pub struct OwnershipArbiter {
    owners: BTreeMap<RegionId, Claim>,
    contest_window_us: u64,
}

impl Default for OwnershipArbiter {
    fn default() -> Self {
        Self::new(DEFAULT_CONTEST_WINDOW_US)
    }
}

impl OwnershipArbiter {
    pub fn new(contest_window_us: u64) -> Self {
        Self {
            owners: BTreeMap::new(),
            contest_window_us,
        }
    }

    /// Owner of a region.
    pub fn owner(&self, region: RegionId) -> Option<SiteId> {
        self.owners.get(&region).map(|c| c.site)
    }

    /// All current owners, by region.
    pub fn owners(&self) -> Vec<RegionOwner> {
        self.owners
            .iter()
            .map(|(&region, c)| RegionOwner {
                region,
                site: c.site,
            })
            .collect()
    }

    /// Regions owned by `site`.
    pub fn regions_of(&self, site: SiteId) -> Vec<RegionId> {
        self.owners
            .iter()
            .filter(|(_, c)| c.site == site)
            .map(|(&r, _)| r)
            .collect()
    }

    fn beats(&self, new: &Claim, holder: &Claim, now_us: u64) -> bool {
        let new_instr = new.role == Role::Instructor;
        let holder_instr = holder.role == Role::Instructor;
        if new_instr != holder_instr {
            return new_instr;
        }
        let fresh = now_us.saturating_sub(holder.granted_at_us) <= self.contest_window_us;
        let earlier = (new.claim_time_us, new.site) < (holder.claim_time_us, holder.site);
        fresh && earlier
    }

    /// Handle a request by `site` (with role `role`) at coordinator time `now_us`.
    pub fn request(
        &mut self,
        site: SiteId,
        role: Role,
        req: OwnershipRequest,
        now_us: u64,
    ) -> OwnershipOutcome {
        let region = req.region;
        if role == Role::Observer {
            return OwnershipOutcome::Deny {
                to: site,
                deny: OwnershipDeny {
                    region,
                    holder: self.owner(region),
                    reason: DenyReason::ObserverCannotOwn,
                },
            };
        }
        let claim = Claim {
            site,
            role,
            claim_time_us: req
                .claim_time_us
                .clamp(now_us.saturating_sub(self.contest_window_us), now_us),
            granted_at_us: now_us,
        };
        match self.owners.get(&region).copied() {
            None => {
                self.owners.insert(region, claim);
                OwnershipOutcome::Grant(OwnershipGrant {
                    region,
                    site,
                    previous: None,
                })
            }
            Some(holder) if holder.site == site => {
                // Idempotent re-request: keep the original claim.
                OwnershipOutcome::Grant(OwnershipGrant {
                    region,
                    site,
                    previous: None,
                })
            }
            Some(holder) => {
                if self.beats(&claim, &holder, now_us) {
                    self.owners.insert(region, claim);
                    OwnershipOutcome::Grant(OwnershipGrant {
                        region,
                        site,
                        previous: Some(holder.site),
                    })
                } else {
                    OwnershipOutcome::Deny {
                        to: site,
                        deny: OwnershipDeny {
                            region,
                            holder: Some(holder.site),
                            reason: DenyReason::HeldByOther,
                        },
                    }
                }
            }
        }
    }

    /// `site` releases `region`.
    pub fn release(&mut self, site: SiteId, region: RegionId) -> OwnershipOutcome {
        match self.owners.get(&region) {
            Some(c) if c.site == site => {
                self.owners.remove(&region);
                OwnershipOutcome::Release(OwnershipRelease { region, site })
            }
            other => OwnershipOutcome::Deny {
                to: site,
                deny: OwnershipDeny {
                    region,
                    holder: other.map(|c| c.site),
                    reason: DenyReason::NotOwner,
                },
            },
        }
    }

    /// A site left: all its regions are released (broadcast the returned releases).
    pub fn site_left(&mut self, site: SiteId) -> Vec<OwnershipRelease> {
        let regions = self.regions_of(site);
        for r in &regions {
            self.owners.remove(r);
        }
        regions
            .into_iter()
            .map(|region| OwnershipRelease { region, site })
            .collect()
    }

    /// Forget all ownership (scene reset).
    pub fn clear(&mut self) {
        self.owners.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn req(region: RegionId, t: u64) -> OwnershipRequest {
        OwnershipRequest {
            region,
            claim_time_us: t,
        }
    }

    fn granted(o: OwnershipOutcome) -> OwnershipGrant {
        match o {
            OwnershipOutcome::Grant(g) => g,
            other => panic!("expected grant, got {other:?}"),
        }
    }

    fn denied(o: OwnershipOutcome) -> OwnershipDeny {
        match o {
            OwnershipOutcome::Deny { deny, .. } => deny,
            other => panic!("expected deny, got {other:?}"),
        }
    }

    #[test]
    fn free_region_granted_and_idempotent() {
        let mut a = OwnershipArbiter::default();
        let g = granted(a.request(1, Role::Trainee, req(7, 1000), 1000));
        assert_eq!((g.region, g.site, g.previous), (7, 1, None));
        let g = granted(a.request(1, Role::Trainee, req(7, 2000), 2000));
        assert_eq!(g.previous, None);
        assert_eq!(a.owner(7), Some(1));
    }

    #[test]
    fn established_holder_keeps_region_against_trainee() {
        let mut a = OwnershipArbiter::default();
        granted(a.request(1, Role::Trainee, req(7, 0), 0));
        let now = 1_000_000;
        let d = denied(a.request(2, Role::Trainee, req(7, now), now));
        assert_eq!(d.holder, Some(1));
        assert_eq!(d.reason, DenyReason::HeldByOther);
        assert_eq!(a.owner(7), Some(1));
    }

    #[test]
    fn instructor_wins_conflict() {
        let mut a = OwnershipArbiter::default();
        granted(a.request(1, Role::Trainee, req(7, 0), 0));
        let g = granted(a.request(5, Role::Instructor, req(7, 5_000_000), 5_000_000));
        assert_eq!((g.site, g.previous), (5, Some(1)));
        // and keeps it against trainees, even with an earlier claim inside the window
        let d = denied(a.request(1, Role::Trainee, req(7, 4_999_990), 5_000_010));
        assert_eq!(d.holder, Some(5));
        assert_eq!(a.owner(7), Some(5));
    }

    #[test]
    fn earlier_claim_wins_when_requests_cross() {
        let mut a = OwnershipArbiter::default();
        // site 2 touched at t=1000 but its request arrives second
        granted(a.request(1, Role::Trainee, req(7, 1500), 2000));
        let g = granted(a.request(2, Role::Trainee, req(7, 1000), 2100));
        assert_eq!((g.site, g.previous), (2, Some(1)));
        // later claim loses
        let d = denied(a.request(1, Role::Trainee, req(7, 1500), 2200));
        assert_eq!(d.holder, Some(2));
    }

    #[test]
    fn equal_claims_break_ties_by_site_id() {
        let mut a = OwnershipArbiter::default();
        granted(a.request(3, Role::Trainee, req(7, 1000), 1000));
        let g = granted(a.request(2, Role::Trainee, req(7, 1000), 1010));
        assert_eq!(g.site, 2);
        denied(a.request(3, Role::Trainee, req(7, 1000), 1020));
    }

    #[test]
    fn claims_in_the_distant_past_are_clamped() {
        let mut a = OwnershipArbiter::default();
        let now = 10_000_000;
        granted(a.request(1, Role::Trainee, req(7, now - 80_000), now));
        // site 2 pretends it touched the region 10 s ago: its claim is clamped to
        // (now + 90 ms) − 100 ms = now − 10 ms, later than the holder's claim.
        denied(a.request(2, Role::Trainee, req(7, 0), now + 90_000));
    }

    #[test]
    fn two_instructors_earlier_claim() {
        let mut a = OwnershipArbiter::default();
        granted(a.request(1, Role::Instructor, req(7, 0), 0));
        denied(a.request(2, Role::Instructor, req(7, 1_000_000), 1_000_000));
    }

    #[test]
    fn observers_never_own() {
        let mut a = OwnershipArbiter::default();
        let d = denied(a.request(1, Role::Observer, req(7, 0), 0));
        assert_eq!(d.reason, DenyReason::ObserverCannotOwn);
        assert_eq!(a.owner(7), None);
    }

    #[test]
    fn release_by_owner_only() {
        let mut a = OwnershipArbiter::default();
        granted(a.request(1, Role::Trainee, req(7, 0), 0));
        let o = a.release(2, 7);
        assert_eq!(o.recipient(), Some(2));
        assert_eq!(denied(o).reason, DenyReason::NotOwner);
        let o = a.release(1, 7);
        assert_eq!(o.recipient(), None);
        assert_eq!(
            o,
            OwnershipOutcome::Release(OwnershipRelease { region: 7, site: 1 })
        );
        assert_eq!(a.owner(7), None);
        assert_eq!(denied(a.release(1, 7)).holder, None);
    }

    #[test]
    fn site_left_releases_its_regions() {
        let mut a = OwnershipArbiter::default();
        for r in [1, 2, 3] {
            granted(a.request(1, Role::Trainee, req(r, 0), 0));
        }
        granted(a.request(2, Role::Trainee, req(9, 0), 0));
        let rel = a.site_left(1);
        assert_eq!(
            rel.iter().map(|r| r.region).collect::<Vec<_>>(),
            vec![1, 2, 3]
        );
        assert_eq!(a.owners(), vec![RegionOwner { region: 9, site: 2 }]);
        assert!(a.site_left(1).is_empty());
        // now free for others
        granted(a.request(2, Role::Trainee, req(1, 5_000_000), 5_000_000));
    }
}
