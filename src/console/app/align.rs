//! The Align screen's keys: follower jog, home, stop and fault reset; zero.

use super::*;

impl App {
    pub(super) fn follower(
        &mut self,
        action: FollowerAction,
        mm: Option<f64>,
        what: String,
    ) -> Vec<Action> {
        if !self.may_operate(&what) {
            return Vec::new();
        }
        vec![self.send(Request::Follower { action, mm }, Pending::Other(what))]
    }

    pub(super) fn align_key(&mut self, key: KeyEvent) -> Vec<Action> {
        let step = self.jog_step_mm;
        match key_char(&key) {
            Some('h') => self.follower(FollowerAction::Home, None, "home the follower".into()),
            Some('j') => self.follower(
                FollowerAction::Jog,
                Some(-step),
                format!("jog the follower -{step} mm"),
            ),
            Some('k') => self.follower(
                FollowerAction::Jog,
                Some(step),
                format!("jog the follower +{step} mm"),
            ),
            Some('x') => self.follower(FollowerAction::Stop, None, "stop the follower".into()),
            Some('r') => self.follower(
                FollowerAction::FaultReset,
                None,
                "reset the follower's fault".into(),
            ),
            Some('z') => {
                if !self.may_operate("zero") {
                    return Vec::new();
                }
                vec![self.send(Request::Zero, Pending::Other("zero here".into()))]
            }
            Some('c') => {
                if !self.may_operate("clear zero") {
                    return Vec::new();
                }
                vec![self.send(Request::ClearZero, Pending::Other("clear the zero".into()))]
            }
            Some('+' | ']') => {
                self.jog_step_mm = (step * 10.0).min(10.0);
                self.say(Level::Info, format!("jog step {} mm", self.jog_step_mm));
                Vec::new()
            }
            Some('-' | '[') => {
                self.jog_step_mm = (step / 10.0).max(0.001);
                self.say(Level::Info, format!("jog step {} mm", self.jog_step_mm));
                Vec::new()
            }
            _ => Vec::new(),
        }
    }
}
