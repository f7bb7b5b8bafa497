//! The Publish screen's state and keys: stored tables, generation, publication.

use super::*;

/// The Publish screen: the stored tables, what the PLC holds, generation and publication.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PublishState {
    /// Newest first, as `table_list` gives them.
    pub tables: Vec<TableView>,
    /// The CNC map the service fits tables to.
    pub map: Option<String>,
    /// Whether a `table_list` reply came.
    pub listed: bool,
    pub selected: usize,
    /// The last `table_status`, or why it failed.
    pub status: Option<Result<StatusView, String>>,
    /// Picking the run to generate tables from: the index into [`PublishState::runs`].
    pub picking: Option<usize>,
    /// Tables being generated from this run.
    pub generating: Option<i64>,
    /// The table being published (until the reply).
    pub publishing: Option<i64>,
    /// The last publication's outcome (the service's reply), or why it failed.
    pub outcome: Option<Result<PublishView, String>>,
}

impl PublishState {
    pub fn selected_table(&self) -> Option<&TableView> {
        self.tables.get(self.selected)
    }
    /// The finished runs tables can be generated from.
    pub fn runs(results: &ResultsView) -> Vec<&RunSummary> {
        results
            .runs
            .iter()
            .filter(|r| r.state == "finished")
            .collect()
    }
}

impl App {
    pub(super) fn publish_key(&mut self, key: KeyEvent) -> Vec<Action> {
        if let Some(i) = self.publish.picking {
            let runs: Vec<i64> = PublishState::runs(&self.results)
                .iter()
                .map(|r| r.id)
                .collect();
            let n = runs.len();
            match key.code {
                KeyCode::Up if n > 0 => self.publish.picking = Some((i + n - 1) % n),
                KeyCode::Down if n > 0 => self.publish.picking = Some((i + 1) % n),
                KeyCode::Esc => self.publish.picking = None,
                KeyCode::Enter => {
                    let Some(&run) = runs.get(i) else {
                        self.say(Level::Info, "no finished run to generate tables from");
                        return Vec::new();
                    };
                    self.publish.picking = None;
                    if !self.may_operate("generating tables") {
                        return Vec::new();
                    }
                    self.publish.generating = Some(run);
                    self.log(Level::Info, format!("→ generate tables from run {run}"));
                    return vec![self.send(
                        Request::TableGenerate {
                            run_id: run,
                            residual_only: false,
                        },
                        Pending::Generate(run),
                    )];
                }
                _ => {}
            }
            return Vec::new();
        }
        let n = self.publish.tables.len();
        match (key.code, key_char(&key)) {
            (KeyCode::Up, _) if n > 0 => {
                self.publish.selected = (self.publish.selected + n - 1) % n
            }
            (KeyCode::Down, _) if n > 0 => self.publish.selected = (self.publish.selected + 1) % n,
            (_, Some('r')) => return self.reload_publish(),
            (_, Some('g')) if self.may_operate("generating tables") => {
                self.publish.picking = Some(0);
                self.results.listed = false;
                if !self.waiting(&Pending::Runs) {
                    return vec![self.send(Request::Runs { limit: None }, Pending::Runs)];
                }
            }
            (_, Some('p')) => {
                if self.publish.publishing.is_some() {
                    self.say(
                        Level::Warn,
                        "a publication is under way: wait for its outcome",
                    );
                } else if let Some(t) = self.publish.selected_table() {
                    let (table_id, axis) = (t.id, t.axis.clone());
                    if self.may_operate("publishing a table") {
                        self.overlay = Overlay::Input(Input {
                            purpose: InputFor::PublishAxis { table_id, axis },
                            text: String::new(),
                        });
                    }
                } else {
                    self.say(Level::Info, "no stored table: generate one from a run (g)");
                }
            }
            _ => {}
        }
        Vec::new()
    }
}
