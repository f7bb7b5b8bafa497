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
