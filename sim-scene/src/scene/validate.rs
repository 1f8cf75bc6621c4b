//! Validation of a parsed scene: every value that can be checked without the lattice
//! ([`Scene::validate`]), and the node selections of fix and load boxes once node
//! positions are known ([`Scene::validate_selection`]).

use std::collections::BTreeSet;

use nalgebra::Vector3;

use super::{Aabb, FORMAT_VERSION, NodeSelection, Scene, SceneError};

fn check_vec(file: &str, key: &str, v: &Vector3<f64>) -> Result<(), SceneError> {
    if v.iter().all(|c| c.is_finite()) {
        Ok(())
    } else {
        Err(SceneError::invalid(file, key, "must be finite"))
    }
}

fn check_positive(file: &str, key: &str, x: f64, unit: &str) -> Result<(), SceneError> {
    if x.is_finite() && x > 0.0 {
        Ok(())
    } else {
        Err(SceneError::invalid(
            file,
            key,
            format!("must be positive and finite, got {x}{unit}"),
        ))
    }
}

fn check_box(file: &str, key: &str, b: &Aabb, allow_flat: bool) -> Result<(), SceneError> {
    check_vec(file, &format!("{key}.min"), &b.min)?;
    check_vec(file, &format!("{key}.max"), &b.max)?;
    let bad = if allow_flat {
        !b.is_ordered()
    } else {
        b.is_empty()
    };
    if bad {
        return Err(SceneError::invalid(
            file,
            key,
            format!(
                "box is empty: max must be {} min on every axis (min = {:?}, max = {:?})",
                if allow_flat { "≥" } else { ">" },
                b.min.as_slice(),
                b.max.as_slice()
            ),
        ));
    }
    Ok(())
}

impl Scene {
    /// Checks every value that can be checked without reading files or knowing the
    /// lattice. `file` labels errors.
    pub fn validate(&self, file: &str) -> Result<(), SceneError> {
        if let Some(v) = self.version
            && (v == 0 || v > FORMAT_VERSION)
        {
            return Err(SceneError::invalid(
                file,
                "version",
                format!("unsupported format version {v} (this build reads 1..={FORMAT_VERSION})"),
            ));
        }
        check_vec(file, "gravity", &self.gravity)?;
        if let Some(cam) = &self.camera {
            check_vec(file, "camera.position", &cam.position)?;
            check_vec(file, "camera.target", &cam.target)?;
            if (cam.position - cam.target).norm() < 1e-6 {
                return Err(SceneError::invalid(
                    file,
                    "camera.target",
                    "must differ from camera.position (the camera needs a direction)",
                ));
            }
            if !(cam.fov_deg > 1.0 && cam.fov_deg < 170.0) {
                return Err(SceneError::invalid(
                    file,
                    "camera.fov_deg",
                    format!("{} is outside (1, 170) degrees", cam.fov_deg),
                ));
            }
        }
        for (name, m) in &self.materials {
            let k = |f: &str| format!("material.{name}.{f}");
            check_positive(file, &k("young"), m.young, " Pa")?;
            if !(m.poisson > -1.0 && m.poisson < 0.5) {
                return Err(SceneError::invalid(
                    file,
                    k("poisson"),
                    format!("must satisfy -1 < poisson < 0.5, got {}", m.poisson),
                ));
            }
            check_positive(file, &k("density"), m.density, " kg/m^3")?;
            for (f, v) in [
                ("rayleigh_mass", m.rayleigh_mass),
                ("rayleigh_stiffness", m.rayleigh_stiffness),
            ] {
                if !(v.is_finite() && v >= 0.0) {
                    return Err(SceneError::invalid(
                        file,
                        k(f),
                        format!("must be non-negative and finite, got {v}"),
                    ));
                }
            }
        }
        if self.bodies.is_empty() {
            return Err(SceneError::invalid(
                file,
                "body",
                "the scene defines no [[body]]",
            ));
        }
        let material_ok = |key: String, name: &str| {
            if self.materials.contains_key(name) {
                Ok(())
            } else {
                let known: Vec<&str> = self.materials.keys().map(String::as_str).collect();
                Err(SceneError::invalid(
                    file,
                    key,
                    format!("undefined material \"{name}\" (defined: {known:?})"),
                ))
            }
        };
        let mut names = BTreeSet::new();
        for (i, b) in self.bodies.iter().enumerate() {
            let k = |f: &str| format!("body[{i}].{f}");
            if b.name.is_empty() {
                return Err(SceneError::invalid(file, k("name"), "must not be empty"));
            }
            if !names.insert(b.name.as_str()) {
                return Err(SceneError::invalid(
                    file,
                    k("name"),
                    format!("duplicate body name \"{}\"", b.name),
                ));
            }
            match (&b.box_shape, &b.mesh) {
                (Some(_), Some(_)) => {
                    return Err(SceneError::invalid(
                        file,
                        format!("body[{i}]"),
                        "give either `box` or `mesh`, not both",
                    ));
                }
                (None, None) => {
                    return Err(SceneError::invalid(
                        file,
                        format!("body[{i}]"),
                        "needs a shape: `box = { min = [..], max = [..] }` or `mesh = \"file\"`",
                    ));
                }
                (Some(bx), None) => check_box(file, &k("box"), bx, false)?,
                (None, Some(_)) => {}
            }
            check_positive(file, &k("cell"), b.cell, " m")?;
            if b.max_depth > 24 {
                return Err(SceneError::invalid(
                    file,
                    k("max_depth"),
                    format!("must be at most 24, got {}", b.max_depth),
                ));
            }
            material_ok(k("material"), &b.material)?;
            for (j, inc) in b.inclusions.iter().enumerate() {
                let ik = |f: &str| format!("body[{i}].inclusion[{j}].{f}");
                material_ok(ik("material"), &inc.material)?;
                match (&inc.capsules, &inc.mesh) {
                    (Some(_), Some(_)) => {
                        return Err(SceneError::invalid(
                            file,
                            format!("body[{i}].inclusion[{j}]"),
                            "give either `capsules` or `mesh`, not both",
                        ));
                    }
                    (None, None) => {
                        return Err(SceneError::invalid(
                            file,
                            format!("body[{i}].inclusion[{j}]"),
                            "needs `capsules = [{ a = [..], b = [..], radius = .. }, ..]` or `mesh = \"file\"`",
                        ));
                    }
                    (Some(caps), None) => {
                        if caps.is_empty() {
                            return Err(SceneError::invalid(
                                file,
                                ik("capsules"),
                                "must list at least one capsule",
                            ));
                        }
                        for (c, cap) in caps.iter().enumerate() {
                            let ck = format!("body[{i}].inclusion[{j}].capsules[{c}]");
                            check_vec(file, &format!("{ck}.a"), &cap.a)?;
                            check_vec(file, &format!("{ck}.b"), &cap.b)?;
                            check_positive(file, &format!("{ck}.radius"), cap.radius, " m")?;
                        }
                    }
                    (None, Some(_)) => {}
                }
            }
        }
        for (i, f) in self.fixes.iter().enumerate() {
            check_box(file, &format!("fix[{i}].box"), &f.region, true)?;
        }
        for (i, l) in self.loads.iter().enumerate() {
            check_box(file, &format!("load[{i}].box"), &l.region, true)?;
            check_vec(file, &format!("load[{i}].force"), &l.force)?;
        }
        let mut names = BTreeSet::new();
        for (i, p) in self.probes.iter().enumerate() {
            if !names.insert(p.name.as_str()) {
                return Err(SceneError::invalid(
                    file,
                    format!("probe[{i}].name"),
                    format!("duplicate probe name \"{}\"", p.name),
                ));
            }
            check_vec(file, &format!("probe[{i}].point"), &p.point)?;
        }
        let mut names = BTreeSet::new();
        for (i, t) in self.tools.iter().enumerate() {
            let k = |f: &str| format!("tool[{i}].{f}");
            if t.name.is_empty() {
                return Err(SceneError::invalid(file, k("name"), "must not be empty"));
            }
            if !names.insert(t.name.as_str()) {
                return Err(SceneError::invalid(
                    file,
                    k("name"),
                    format!("duplicate tool name \"{}\"", t.name),
                ));
            }
            check_vec(file, &k("position"), &t.position)?;
            let n2: f64 = t.orientation.iter().map(|c| c * c).sum();
            if !(n2.is_finite() && n2 > 1e-12) {
                return Err(SceneError::invalid(
                    file,
                    k("orientation"),
                    "quaternion [w, x, y, z] must be finite and non-zero",
                ));
            }
            check_positive(file, &k("radius"), t.radius, " m")?;
            check_positive(file, &k("length"), t.length, " m")?;
        }
        let mut names = BTreeSet::new();
        for (i, a) in self.attachments.iter().enumerate() {
            let k = |f: &str| format!("attachment[{i}].{f}");
            if !names.insert(a.name.as_str()) || a.name.is_empty() {
                return Err(SceneError::invalid(
                    file,
                    k("name"),
                    format!("must be non-empty and unique, got \"{}\"", a.name),
                ));
            }
            for (j, b) in a.bodies.iter().enumerate() {
                if !self.bodies.iter().any(|body| &body.name == b) {
                    let known: Vec<&str> = self.bodies.iter().map(|b| b.name.as_str()).collect();
                    return Err(SceneError::invalid(
                        file,
                        format!("attachment[{i}].bodies[{j}]"),
                        format!("undefined body \"{b}\" (defined: {known:?})"),
                    ));
                }
            }
            if a.bodies[0] == a.bodies[1] {
                return Err(SceneError::invalid(
                    file,
                    k("bodies"),
                    format!("ties body \"{}\" to itself; name two bodies", a.bodies[0]),
                ));
            }
            check_box(file, &k("box"), &a.region, true)?;
            check_positive(file, &k("stiffness"), a.stiffness, " N/m")?;
            check_positive(file, &k("reach"), a.reach, " m")?;
            check_positive(file, &k("release_radius"), a.release_radius, " m")?;
            for (f, v) in [
                ("release_rate", a.release_rate),
                ("release_force", a.release_force),
            ] {
                if !(v.is_finite() && v >= 0.0) {
                    return Err(SceneError::invalid(
                        file,
                        k(f),
                        format!("must be non-negative and finite, got {v}"),
                    ));
                }
            }
        }
        let s = &self.simulation;
        check_positive(file, "simulation.dt", s.dt, " s")?;
        if s.cg_iterations == 0 {
            return Err(SceneError::invalid(
                file,
                "simulation.cg_iterations",
                "must be at least 1",
            ));
        }
        check_positive(file, "simulation.cg_tolerance", s.cg_tolerance, "")?;
        check_positive(file, "simulation.polar_tolerance", s.polar_tolerance, "")?;
        check_positive(
            file,
            "simulation.contact_stiffness",
            s.contact_stiffness,
            " N/m",
        )?;
        let a = self.features.rotation_sharing_angle_deg;
        if !(a.is_finite() && (0.0..=180.0).contains(&a)) {
            return Err(SceneError::invalid(
                file,
                "features.rotation_sharing_angle_deg",
                format!("must be within [0, 180] degrees, got {a}"),
            ));
        }
        Ok(())
    }

    /// Selects the lattice nodes of every `[[fix]]` and `[[load]]` box. The engine calls
    /// this once node positions are known; a box that selects no node is an error naming
    /// `fix[i].box` / `load[i].box`.
    pub fn validate_selection(
        &self,
        file: &str,
        nodes: &[Vector3<f64>],
    ) -> Result<NodeSelection, SceneError> {
        let select = |key: String, b: &Aabb| -> Result<Vec<usize>, SceneError> {
            let sel: Vec<usize> = nodes
                .iter()
                .enumerate()
                .filter(|(_, p)| b.contains(p))
                .map(|(i, _)| i)
                .collect();
            if sel.is_empty() {
                let range = Aabb::from_points(nodes.iter())
                    .map(|r| format!("{:?}..{:?}", r.min.as_slice(), r.max.as_slice()))
                    .unwrap_or_else(|| "none".into());
                return Err(SceneError::invalid(
                    file,
                    key,
                    format!(
                        "selects no node (box {:?}..{:?}; {} nodes span {range})",
                        b.min.as_slice(),
                        b.max.as_slice(),
                        nodes.len()
                    ),
                ));
            }
            Ok(sel)
        };
        let fixed = self
            .fixes
            .iter()
            .enumerate()
            .map(|(i, f)| select(format!("fix[{i}].box"), &f.region))
            .collect::<Result<_, _>>()?;
        let loaded = self
            .loads
            .iter()
            .enumerate()
            .map(|(i, l)| select(format!("load[{i}].box"), &l.region))
            .collect::<Result<_, _>>()?;
        Ok(NodeSelection { fixed, loaded })
    }
}
