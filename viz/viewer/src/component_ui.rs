//! What the viewer adds to a component's tab, per kind: one registry (as `viz::registry` lists
//! the kinds a pipeline can hold), so the tab's code asks it instead of branching on kind names.

use egui::Ui;
use viz::component::Settings;
use viz::components::rays::RaysSettings;

use crate::query_service::QueryService;
use crate::state::State;

/// The viewer's extras for one component kind.
pub struct ComponentUi {
    /// The kind (its settings' `Settings::KIND`).
    pub kind: &'static str,
    /// Drawn in the component's tab between its report and its settings.
    pub extras: fn(&mut Ui, &mut State, &mut QueryService, u64),
}

/// Every kind with extras in its tab.
pub fn registry() -> &'static [ComponentUi] {
    const UIS: &[ComponentUi] = &[ComponentUi { kind: RaysSettings::KIND, extras: crate::timers::tree_navigation }];
    UIS
}

/// The extras of `kind`, where it has any.
pub fn of(kind: &str) -> Option<&'static ComponentUi> {
    registry().iter().find(|c| c.kind == kind)
}

#[cfg(test)]
mod tests {
    #[test]
    fn every_kind_with_extras_is_a_registered_kind() {
        for c in super::registry() {
            assert!(viz::registry().iter().any(|i| i.kind == c.kind), "{} is not a viz kind", c.kind);
        }
    }
}
