//! The beam alignment's requests (`align_read`, `align_target`, `align_advice`,
//! `align_clear`): the stations an operator reads with the carriage at rest and the advice
//! over a span ([`crate::service::align`], sans-I/O); each advice stored for its axis (off
//! the loop), the newest kept in the cache for the pre-run check. It never holds the machine:
//! the operator moves it.

use super::{Ctx, Procedure, Reply, Who};
use crate::acquire::Frame;
use crate::service::align::{AlignState, station_json};
use crate::service::api::Request;
use crate::store::AlignmentRecord;
use tokio::sync::mpsc;

/// An advice stored (or not): the reply owed, the record and the answer.
struct Stored {
    reply: Reply,
    record: crate::store::NewAlignment,
    answer: serde_json::Value,
    id: Result<i64, String>,
}

/// The alignment's requests.
pub struct Alignment {
    state: AlignState,
    tx: mpsc::Sender<Stored>,
    rx: mpsc::Receiver<Stored>,
}

impl Alignment {
    pub fn new(state: AlignState) -> Alignment {
        let (tx, rx) = mpsc::channel(8);
        Alignment { state, tx, rx }
    }
}

impl Procedure for Alignment {
    fn name(&self) -> &'static str {
        "the beam alignment"
    }

    fn takes(&self, req: &Request) -> bool {
        matches!(
            req,
            Request::AlignRead { .. }
                | Request::AlignTarget { .. }
                | Request::AlignAdvice { .. }
                | Request::AlignClear
                | Request::AlignStored { .. }
        )
    }

    fn holds_machine(&self) -> bool {
        false
    }

    fn busy(&self, what: &str) -> String {
        format!("the beam alignment does not hold the machine: {what}")
    }

    fn on_frame(&mut self, f: &Frame) {
        self.state.handle_frame(f);
    }

    fn request(&mut self, req: Request, _who: &Who, reply: Reply, ctx: &mut Ctx) {
        match req {
            Request::AlignRead { at_mm } => {
                let at = at_mm.or_else(|| ctx.pipeline.measure.position());
                reply.send(match at {
                    Some(at) => self.state.read(at).map(|st| station_json(&st)),
                    None => Err("where is the carriage? give at_mm (the position is measured only after a zero reference)".into()),
                });
            }
            Request::AlignTarget { psd, x, y } => {
                reply.send(self.state.target(psd, x, y).map(|st| station_json(&st)))
            }
            Request::AlignClear => {
                self.state.clear();
                reply.send(Ok(serde_json::json!({"stations": 0})));
            }
            Request::AlignStored { axis } => {
                let axis = axis.unwrap_or_else(|| "X".into());
                reply.send(Ok(ctx
                    .cached
                    .alignments
                    .get(&axis)
                    .map_or(serde_json::Value::Null, stored_json)));
            }
            Request::AlignAdvice {
                from_mm,
                to_mm,
                axis,
            } => {
                let axis = axis.unwrap_or_else(|| "X".into());
                let (record, answer) =
                    match self
                        .state
                        .advise_for(ctx.calibrations.layout(), &axis, (from_mm, to_mm))
                    {
                        Ok(r) => r,
                        Err(e) => return reply.send(Err(e)),
                    };
                let rec = record.clone();
                let tx = self.tx.clone();
                match ctx.store.try_call(move |s| s.insert_alignment(&rec)) {
                    Ok(done) => {
                        tokio::spawn(async move {
                            let id = match done.await {
                                Ok(Ok(id)) => Ok(id),
                                Ok(Err(e)) => Err(e.to_string()),
                                Err(e) => Err(e.to_string()),
                            };
                            let _ = tx
                                .send(Stored {
                                    reply,
                                    record,
                                    answer,
                                    id,
                                })
                                .await;
                        });
                    }
                    Err(e) => reply.send(Err(format!("the advice was not stored: {e}"))),
                }
            }
            _ => reply.send(Err("internal: not an alignment request".into())),
        }
    }

    fn tick(&mut self, ctx: &mut Ctx) {
        while let Ok(s) = self.rx.try_recv() {
            match s.id {
                Ok(id) => {
                    let mut answer = s.answer;
                    answer["alignment_id"] = serde_json::json!(id);
                    ctx.cached.alignments.insert(
                        s.record.axis.clone(),
                        AlignmentRecord {
                            id,
                            unix_us: crate::store::now_us(),
                            alignment: s.record,
                        },
                    );
                    s.reply.send(Ok(answer));
                }
                Err(e) => s.reply.send(Err(format!("the advice was not stored: {e}"))),
            }
        }
    }
}

/// A stored alignment as `align_stored` answers it: its advice as `align_advice` gave it, with
/// the record's id, time and span.
fn stored_json(rec: &AlignmentRecord) -> serde_json::Value {
    let a = &rec.alignment;
    let mut v = match &a.advice {
        serde_json::Value::Object(_) => a.advice.clone(),
        // A record whose advice is not an object: what the record itself says.
        _ => serde_json::json!({"passed": a.passed, "check": a.check}),
    };
    v["axis"] = serde_json::json!(a.axis);
    v["alignment_id"] = serde_json::json!(rec.id);
    v["unix_us"] = serde_json::json!(rec.unix_us);
    v["from_mm"] = serde_json::json!(a.from_mm);
    v["to_mm"] = serde_json::json!(a.to_mm);
    v
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::NewAlignment;

    #[test]
    fn a_stored_alignment_answers_with_its_advice_time_and_span() {
        let advice = serde_json::json!({"passed": true, "check": "every spot stays on its PSD",
            "after": "", "turns": [], "misalignment_urad": [20.0, -5.0], "stations": 2, "text": "t"});
        let rec = AlignmentRecord {
            id: 4,
            unix_us: 1_700_000_000_000_000,
            alignment: NewAlignment {
                axis: "Y".into(),
                from_mm: -1.0,
                to_mm: 400.0,
                passed: true,
                yaw_rad: 20e-6,
                pitch_rad: -5e-6,
                check: "every spot stays on its PSD".into(),
                advice,
            },
        };
        let v = stored_json(&rec);
        assert_eq!(v["alignment_id"], 4);
        assert_eq!(v["axis"], "Y");
        assert_eq!(v["unix_us"], 1_700_000_000_000_000i64);
        assert_eq!(
            (v["from_mm"].as_f64(), v["to_mm"].as_f64()),
            (Some(-1.0), Some(400.0))
        );
        assert_eq!(v["passed"], true);
        assert_eq!(v["misalignment_urad"][0], 20.0);
        // An advice that is not an object still answers with what the record says.
        let odd = AlignmentRecord {
            alignment: NewAlignment {
                advice: serde_json::Value::Null,
                passed: false,
                ..rec.alignment.clone()
            },
            ..rec
        };
        let v = stored_json(&odd);
        assert_eq!(
            (v["passed"].as_bool(), v["check"].as_str()),
            (Some(false), Some("every spot stays on its PSD"))
        );
    }
}
