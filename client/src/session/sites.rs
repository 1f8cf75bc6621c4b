//! The session's site table as this site knows it: its own id and the others.

use std::collections::BTreeMap;

use proto::{Role, SiteEntry, SiteId, Welcome};

/// This site's id (once welcomed) and every site of the session with its name and role.
#[derive(Debug, Default, Clone)]
pub struct SiteTable {
    me: Option<SiteId>,
    /// Our ids before a rejoin: what was sent under them (keyframes kept by the
    /// coordinator for its snapshot) is still ours, not another site's.
    former: Vec<SiteId>,
    sites: BTreeMap<SiteId, (String, Role)>,
    /// Sites that left: their late datagrams do not make them present again.
    departed: std::collections::BTreeSet<SiteId>,
}

impl SiteTable {
    /// A Welcome (first join or rejoin): our id and the table as the coordinator has it.
    pub fn welcome(&mut self, w: &Welcome) {
        if let Some(old) = self.me.filter(|&old| old != w.site) {
            self.former.push(old);
        }
        self.me = Some(w.site);
        self.sites = w
            .sites
            .iter()
            .map(|s| (s.site, (s.name.clone(), s.role)))
            .collect();
    }

    pub fn joined(&mut self, s: SiteEntry) {
        self.departed.remove(&s.site);
        self.sites.insert(s.site, (s.name, s.role));
    }

    pub fn left(&mut self, site: SiteId) {
        self.sites.remove(&site);
        self.departed.insert(site);
    }

    /// Whether `site` left the session (and did not join again under that id).
    pub fn departed(&self, site: SiteId) -> bool {
        self.departed.contains(&site)
    }

    /// Our id; `None` before the Welcome (or without a link).
    pub fn me(&self) -> Option<SiteId> {
        self.me
    }

    /// Whether `site` is another site than ours.
    pub fn is_other(&self, site: SiteId) -> bool {
        self.me != Some(site) && !self.former.contains(&site)
    }

    /// Whether the table lists `site`.
    pub fn contains(&self, site: SiteId) -> bool {
        self.sites.contains_key(&site)
    }

    pub fn is_empty(&self) -> bool {
        self.sites.is_empty()
    }

    /// Sites in the session, ours included.
    pub fn len(&self) -> usize {
        self.sites.len()
    }

    /// The sites that receive our frames (all others).
    pub fn receivers(&self) -> impl Iterator<Item = SiteId> + '_ {
        self.sites.keys().copied().filter(|s| Some(*s) != self.me)
    }

    pub fn role(&self, site: SiteId) -> Option<Role> {
        self.sites.get(&site).map(|(_, r)| *r)
    }

    pub fn name(&self, site: SiteId) -> Option<&str> {
        self.sites.get(&site).map(|(n, _)| n.as_str())
    }
}
