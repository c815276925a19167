//! A typed client for one simulator session (see `dsrl/simulator/v1/simulator.proto`): open K environments, reset
//! and step them with plain slices, and get decoded arrays back. Used by the server's worker pool, the benchmark
//! and the tests; requests can be pipelined with [`SimulatorSession::send_step`] + [`SimulatorSession::receive`].

use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;
use tonic::{Status, Streaming};

use dsrl_proto::simulator::v1::{
    self as pb, DType, SessionRequest, SessionResponse, TaskSpec, Tensor, session_request, session_response,
    simulator_client::SimulatorClient,
};

/// What one step of n environments returned, decoded.
#[derive(Debug, Clone, PartialEq)]
pub struct StepResult {
    pub envs: Vec<u32>,
    /// `[n * obs_dim]`, row-major.
    pub observations: Vec<f32>,
    pub rewards: Vec<f64>,
    pub costs: Vec<f64>,
    pub terminated: Vec<bool>,
    pub truncated: Vec<bool>,
    /// With `AUTO_RESET_SAME_STEP`: the finished episodes' last observations (zeros for the others).
    pub final_observations: Option<Vec<f32>>,
    /// `[n * act_dim]`: what the simulator applied (the client's actions clipped, or a controller's).
    pub applied_actions: Vec<f32>,
}

/// The rest of one episode its controller drove (see `Drive` in the proto): `T` steps to the episode's end.
#[derive(Debug, Clone, PartialEq)]
pub struct DrivenRest {
    pub env: u32,
    /// `[T * obs_dim]`, row-major: the observation after each step.
    pub observations: Vec<f32>,
    /// `[T * act_dim]`: what the controller applied.
    pub applied_actions: Vec<f32>,
    pub rewards: Vec<f64>,
    pub costs: Vec<f64>,
    pub terminated: bool,
    pub truncated: bool,
}

/// A decoded response to one pipelined request.
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    Reset {
        envs: Vec<u32>,
        observations: Vec<f32>,
    },
    Step(StepResult),
    Drive(Vec<DrivenRest>),
    Render(RenderedFrames),
    /// The session took the policy of an `Act`.
    Acting,
    Played(Played),
    Closed,
}

/// What one `Play` did: the steps its environments took, and the episodes that ended at the last of them.
#[derive(Debug, Clone, PartialEq)]
pub struct Played {
    pub steps: u32,
    pub ended: Vec<PlayedEpisode>,
}

/// An episode a session's policy played to its end: its environment and returns, summed in the worker.
#[derive(Debug, Clone, PartialEq)]
pub struct PlayedEpisode {
    pub env: u32,
    pub reward_return: f64,
    pub cost_return: f64,
    pub length: u32,
}

/// The images a `Render` asked for: `frames` is `[n * height * width * 3]` RGB bytes, one image per environment in
/// the request's order, rows top to bottom.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderedFrames {
    pub envs: Vec<u32>,
    pub width: u32,
    pub height: u32,
    pub frames: Vec<u8>,
}

pub struct SimulatorSession {
    requests: mpsc::Sender<SessionRequest>,
    responses: Streaming<SessionResponse>,
    next_id: u64,
    spec: TaskSpec,
    num_envs: usize,
    /// What each request in flight asked for, in order: every answer is checked against it before it is used.
    pending: std::collections::VecDeque<Asked>,
}

/// A request in flight: what kind, for which environments (already resolved: empty means all).
#[derive(Debug, Clone)]
enum Asked {
    Step(Vec<u32>),
    Reset(Vec<u32>),
    Drive(Vec<u32>),
    Render { envs: Vec<u32>, width: u32, height: u32 },
    Act,
    Play(Vec<u32>),
    Close,
    Raw,
}

/// A worker's answer that does not fit its request: an error for that session (the worker is at fault, not the
/// policy), never a panic where the answer is indexed.
fn bad_answer(message: String) -> Status {
    Status::data_loss(format!("the simulator worker answered out of protocol: {message}"))
}

impl SimulatorSession {
    /// Opens a session; returns it with the K initial observations (`[K * obs_dim]`).
    pub async fn open(channel: Channel, open: pb::Open) -> Result<(SimulatorSession, Vec<f32>), Status> {
        let (requests, receiver) = mpsc::channel(64);
        let num_envs = open.num_envs as usize;
        requests
            .send(SessionRequest {
                id: 0,
                kind: Some(session_request::Kind::Open(open)),
            })
            .await
            .map_err(|_| Status::internal("session request channel closed"))?;
        let mut client = SimulatorClient::new(channel)
            .max_decoding_message_size(256 << 20)
            .max_encoding_message_size(256 << 20);
        let mut responses = client.session(ReceiverStream::new(receiver)).await?.into_inner();
        let first = next_response(&mut responses).await?;
        let Some(session_response::Kind::Opened(opened)) = first.kind else {
            return Err(Status::internal("the worker did not answer Open with Opened"));
        };
        let spec = opened
            .spec
            .ok_or_else(|| Status::internal("Opened without a task spec"))?;
        let observations = opened
            .observations
            .ok_or_else(|| Status::internal("Opened without observations"))?
            .to_f32("observations")?;
        Ok((
            SimulatorSession {
                requests,
                responses,
                next_id: 1,
                spec,
                num_envs,
                pending: std::collections::VecDeque::new(),
            },
            observations,
        ))
    }

    pub fn spec(&self) -> &TaskSpec {
        &self.spec
    }

    pub fn num_envs(&self) -> usize {
        self.num_envs
    }

    /// The environments a request names (empty: all of the session's).
    fn resolve(&self, envs: &[u32]) -> Vec<u32> {
        if envs.is_empty() {
            (0..self.num_envs as u32).collect()
        } else {
            envs.to_vec()
        }
    }

    async fn send(&mut self, kind: session_request::Kind) -> Result<u64, Status> {
        let asked = match &kind {
            session_request::Kind::Step(step) => Asked::Step(self.resolve(&step.envs)),
            session_request::Kind::Reset(reset) => Asked::Reset(self.resolve(&reset.envs)),
            session_request::Kind::Drive(drive) => Asked::Drive(self.resolve(&drive.envs)),
            session_request::Kind::Render(render) => Asked::Render {
                envs: self.resolve(&render.envs),
                width: render.width,
                height: render.height,
            },
            session_request::Kind::Act(_) => Asked::Act,
            session_request::Kind::Play(play) => Asked::Play(self.resolve(&play.envs)),
            session_request::Kind::Close(_) => Asked::Close,
            _ => Asked::Raw,
        };
        self.pending.push_back(asked);
        let id = self.next_id;
        self.next_id += 1;
        if self
            .requests
            .send(SessionRequest { id, kind: Some(kind) })
            .await
            .is_err()
        {
            // The request stream only closes when the worker ended the session; its status says why.
            return Err(match self.responses.message().await {
                Err(status) => status,
                Ok(_) => Status::unavailable("the simulator session ended"),
            });
        }
        Ok(id)
    }

    /// Queues a step without waiting for its result (pipelining); [`Self::receive`] returns results in order.
    pub async fn send_step(&mut self, envs: &[u32], actions: &[f32]) -> Result<u64, Status> {
        let rows = if envs.is_empty() { self.num_envs } else { envs.len() };
        let act_dim = actions.len().checked_div(rows).unwrap_or(0);
        let actions = Tensor::from_f32(&[rows, act_dim], actions);
        self.send(session_request::Kind::Step(pb::Step {
            envs: envs.to_vec(),
            actions: Some(actions),
        }))
        .await
    }

    pub async fn send_reset(&mut self, envs: &[u32], seeds: &[u64]) -> Result<u64, Status> {
        self.send_reset_with(envs, seeds, None).await
    }

    /// [`Self::send_reset`], switching the reset environments to `controller`'s driver (a session opened with one
    /// only).
    pub async fn send_reset_with(
        &mut self,
        envs: &[u32],
        seeds: &[u64],
        controller: Option<pb::Controller>,
    ) -> Result<u64, Status> {
        self.send(session_request::Kind::Reset(pb::Reset {
            envs: envs.to_vec(),
            seeds: seeds.to_vec(),
            controller,
        }))
        .await
    }

    /// Queues a drive (the controller plays the rest of each named environment's episode) without waiting.
    pub async fn send_drive(&mut self, envs: &[u32]) -> Result<u64, Status> {
        self.send(session_request::Kind::Drive(pb::Drive { envs: envs.to_vec() }))
            .await
    }

    /// Queues a render (an RGB image of each named environment as it is now, `width` x `height` pixels) without
    /// waiting; drawing changes no episode.
    pub async fn send_render(&mut self, envs: &[u32], width: u32, height: u32) -> Result<u64, Status> {
        self.send(session_request::Kind::Render(pb::Render {
            envs: envs.to_vec(),
            width,
            height,
        }))
        .await
    }

    /// Queues an `Act`: the session's policy from here on (`config` and `weights` as a checkpoint stores them),
    /// at `cost_threshold`, each forward pass held to `act_cpu_seconds` of the worker's CPU time.
    pub async fn send_act(
        &mut self,
        config: &[u8],
        weights: &[u8],
        cost_threshold: f64,
        act_cpu_seconds: f64,
    ) -> Result<u64, Status> {
        self.send(session_request::Kind::Act(pb::Act {
            config: config.to_vec(),
            weights: weights.to_vec(),
            cost_threshold,
            act_cpu_seconds,
        }))
        .await
    }

    /// Queues a `Play` of the named environments (empty: all): the session's policy steps them until an episode
    /// of theirs ends.
    pub async fn send_play(&mut self, envs: &[u32]) -> Result<u64, Status> {
        self.send(session_request::Kind::Play(pb::Play { envs: envs.to_vec() }))
            .await
    }

    /// Sends a raw request (tests use it to send what a typed call never would).
    pub async fn send_raw(&mut self, kind: session_request::Kind) -> Result<u64, Status> {
        self.send(kind).await
    }

    /// The next answer, in the order the requests were sent, checked against its request: one row per environment
    /// asked for, in that order, with the spec's dimensions, finite observations, rewards and costs (costs also
    /// non-negative). An answer that does not fit is an error (`DATA_LOSS`, naming what was wrong).
    pub async fn receive(&mut self) -> Result<Reply, Status> {
        let reply = self.receive_unchecked().await?;
        let asked = self.pending.pop_front();
        if let Some(asked) = asked {
            self.check(&asked, &reply)?;
        }
        Ok(reply)
    }

    fn check(&self, asked: &Asked, reply: &Reply) -> Result<(), Status> {
        let (obs_dim, act_dim) = (self.spec.obs_dim as usize, self.spec.act_dim as usize);
        let rows = |what: &str, got: usize, want: usize| {
            if got == want {
                Ok(())
            } else {
                Err(bad_answer(format!("{what}: {got} values where {want} were due")))
            }
        };
        fn finite(what: &str, values: impl IntoIterator<Item = f64>) -> Result<(), Status> {
            match values.into_iter().position(|v| !v.is_finite()) {
                Some(i) => Err(bad_answer(format!("{what}: a non-finite value at index {i}"))),
                None => Ok(()),
            }
        }
        match (asked, reply) {
            (Asked::Step(envs), Reply::Step(r)) => {
                if &r.envs != envs {
                    return Err(bad_answer(format!(
                        "a step for environments {envs:?} answered for {:?}",
                        r.envs
                    )));
                }
                let n = envs.len();
                rows("observations", r.observations.len(), n * obs_dim)?;
                rows("rewards", r.rewards.len(), n)?;
                rows("costs", r.costs.len(), n)?;
                rows("terminated", r.terminated.len(), n)?;
                rows("truncated", r.truncated.len(), n)?;
                rows("applied_actions", r.applied_actions.len(), n * act_dim)?;
                if let Some(f) = &r.final_observations {
                    rows("final_observations", f.len(), n * obs_dim)?;
                }
                finite("observations", r.observations.iter().map(|&v| f64::from(v)))?;
                finite("rewards", r.rewards.iter().copied())?;
                finite("costs", r.costs.iter().copied())?;
                if let Some(c) = r.costs.iter().find(|&&c| c < 0.0) {
                    return Err(bad_answer(format!("costs: a negative cost {c}")));
                }
                Ok(())
            }
            (
                Asked::Reset(envs),
                Reply::Reset {
                    envs: got,
                    observations,
                },
            ) => {
                if got != envs {
                    return Err(bad_answer(format!(
                        "a reset of environments {envs:?} answered for {got:?}"
                    )));
                }
                rows("observations", observations.len(), envs.len() * obs_dim)?;
                finite("observations", observations.iter().map(|&v| f64::from(v)))
            }
            (Asked::Drive(envs), Reply::Drive(episodes)) => {
                let got: Vec<u32> = episodes.iter().map(|e| e.env).collect();
                if &got != envs {
                    return Err(bad_answer(format!(
                        "a drive of environments {envs:?} answered for {got:?}"
                    )));
                }
                for e in episodes {
                    let t = e.rewards.len();
                    rows("driven observations", e.observations.len(), t * obs_dim)?;
                    rows("driven costs", e.costs.len(), t)?;
                    rows("driven applied_actions", e.applied_actions.len(), t * act_dim)?;
                }
                Ok(())
            }
            (Asked::Render { envs, width, height }, Reply::Render(r)) => {
                if &r.envs != envs || (r.width, r.height) != (*width, *height) {
                    return Err(bad_answer(format!(
                        "a render of environments {envs:?} at {width}x{height} answered for {:?} at {}x{}",
                        r.envs, r.width, r.height
                    )));
                }
                Ok(())
            }
            (Asked::Play(envs), Reply::Played(played)) => {
                // The ended episodes are among those played, in their order, each with finite returns, a cost
                // return of at least 0 and a length that covers the steps played.
                let mut rest = envs.iter();
                for e in &played.ended {
                    if !rest.any(|&env| env == e.env) {
                        return Err(bad_answer(format!(
                            "a play of environments {envs:?} ended an episode of environment {} (or out of order)",
                            e.env
                        )));
                    }
                    finite("played returns", [e.reward_return, e.cost_return])?;
                    if e.cost_return < 0.0 || e.length < played.steps {
                        return Err(bad_answer(format!(
                            "environment {} ended an episode of {} steps with cost return {} after {} steps played",
                            e.env, e.length, e.cost_return, played.steps
                        )));
                    }
                }
                if played.steps == 0 || played.ended.is_empty() {
                    return Err(bad_answer(format!(
                        "a play answered after {} steps with {} ended episodes",
                        played.steps,
                        played.ended.len()
                    )));
                }
                Ok(())
            }
            (Asked::Act, Reply::Acting) | (Asked::Close, Reply::Closed) | (Asked::Raw, _) => Ok(()),
            (asked, reply) => Err(bad_answer(format!(
                "a {} request was answered with a {} reply",
                match asked {
                    Asked::Step(_) => "step",
                    Asked::Reset(_) => "reset",
                    Asked::Drive(_) => "drive",
                    Asked::Render { .. } => "render",
                    Asked::Act => "act",
                    Asked::Play(_) => "play",
                    Asked::Close => "close",
                    Asked::Raw => "raw",
                },
                match reply {
                    Reply::Step(_) => "step",
                    Reply::Reset { .. } => "reset",
                    Reply::Drive(_) => "drive",
                    Reply::Render(_) => "render",
                    Reply::Acting => "acting",
                    Reply::Played(_) => "played",
                    Reply::Closed => "closed",
                }
            ))),
        }
    }

    async fn receive_unchecked(&mut self) -> Result<Reply, Status> {
        let response = next_response(&mut self.responses).await?;
        match response.kind {
            Some(session_response::Kind::Reset(reset)) => Ok(Reply::Reset {
                envs: reset.envs,
                observations: required(reset.observations, "observations")?.to_f32("observations")?,
            }),
            Some(session_response::Kind::Step(step)) => Ok(Reply::Step(StepResult {
                envs: step.envs,
                observations: required(step.observations, "observations")?.to_f32("observations")?,
                rewards: required(step.rewards, "rewards")?.to_f64("rewards")?,
                costs: required(step.costs, "costs")?.to_f64("costs")?,
                terminated: required(step.terminated, "terminated")?.to_bool("terminated")?,
                truncated: required(step.truncated, "truncated")?.to_bool("truncated")?,
                final_observations: step
                    .final_observations
                    .map(|t| t.to_f32("final_observations"))
                    .transpose()?,
                applied_actions: required(step.applied_actions, "applied_actions")?.to_f32("applied_actions")?,
            })),
            Some(session_response::Kind::Drive(driven)) => Ok(Reply::Drive(
                driven
                    .episodes
                    .into_iter()
                    .map(|e| {
                        Ok(DrivenRest {
                            env: e.env,
                            observations: required(e.observations, "observations")?.to_f32("observations")?,
                            applied_actions: required(e.applied_actions, "applied_actions")?
                                .to_f32("applied_actions")?,
                            rewards: required(e.rewards, "rewards")?.to_f64("rewards")?,
                            costs: required(e.costs, "costs")?.to_f64("costs")?,
                            terminated: e.terminated,
                            truncated: e.truncated,
                        })
                    })
                    .collect::<Result<_, Status>>()?,
            )),
            Some(session_response::Kind::Render(rendered)) => {
                let frames = required(rendered.frames, "frames")?;
                frames.check("frames", DType::Uint8, 1)?;
                let [n, height, width, 3] = frames.shape[..] else {
                    return Err(bad_answer(format!(
                        "frames of shape {:?}, not [n, height, width, 3]",
                        frames.shape
                    )));
                };
                if n != rendered.envs.len() as u64 {
                    return Err(bad_answer(format!(
                        "{n} frames for {} environments",
                        rendered.envs.len()
                    )));
                }
                Ok(Reply::Render(RenderedFrames {
                    envs: rendered.envs,
                    width: u32::try_from(width).map_err(|_| bad_answer("a frame too wide".into()))?,
                    height: u32::try_from(height).map_err(|_| bad_answer("a frame too tall".into()))?,
                    frames: frames.data,
                }))
            }
            Some(session_response::Kind::Act(_)) => Ok(Reply::Acting),
            Some(session_response::Kind::Play(played)) => Ok(Reply::Played(Played {
                steps: played.steps,
                ended: played
                    .ended
                    .into_iter()
                    .map(|e| PlayedEpisode {
                        env: e.env,
                        reward_return: e.reward_return,
                        cost_return: e.cost_return,
                        length: e.length,
                    })
                    .collect(),
            })),
            Some(session_response::Kind::Closed(_)) => Ok(Reply::Closed),
            _ => Err(Status::internal("unexpected response in a simulator session")),
        }
    }

    /// Steps the given environments (empty: all) with row-major actions `[n * act_dim]`.
    pub async fn step(&mut self, envs: &[u32], actions: &[f32]) -> Result<StepResult, Status> {
        self.send_step(envs, actions).await?;
        match self.receive().await? {
            Reply::Step(result) => Ok(result),
            _ => Err(Status::internal("a step was not answered with a transition")),
        }
    }

    /// Resets the given environments (empty: all) with one seed each; returns their observations.
    pub async fn reset(&mut self, envs: &[u32], seeds: &[u64]) -> Result<Vec<f32>, Status> {
        self.reset_with(envs, seeds, None).await
    }

    /// [`Self::reset`], switching the reset environments to `controller`'s driver (a session opened with one only).
    pub async fn reset_with(
        &mut self,
        envs: &[u32],
        seeds: &[u64],
        controller: Option<pb::Controller>,
    ) -> Result<Vec<f32>, Status> {
        self.send_reset_with(envs, seeds, controller).await?;
        match self.receive().await? {
            Reply::Reset { observations, .. } => Ok(observations),
            _ => Err(Status::internal("a reset was not answered with observations")),
        }
    }

    /// Lets the session's controller play the rest of each named environment's episode (empty: all); returns them
    /// in the request's order. A session opened with a controller and without auto-reset only.
    pub async fn drive(&mut self, envs: &[u32]) -> Result<Vec<DrivenRest>, Status> {
        self.send_drive(envs).await?;
        match self.receive().await? {
            Reply::Drive(episodes) => Ok(episodes),
            _ => Err(Status::internal("a drive was not answered with driven episodes")),
        }
    }

    /// Draws the named environments (empty: all) as they are now; see [`Self::send_render`].
    pub async fn render(&mut self, envs: &[u32], width: u32, height: u32) -> Result<RenderedFrames, Status> {
        self.send_render(envs, width, height).await?;
        match self.receive().await? {
            Reply::Render(frames) => Ok(frames),
            _ => Err(Status::internal("a render was not answered with frames")),
        }
    }

    /// Closes the session and waits for the worker to confirm that its environments are freed.
    pub async fn close(mut self) -> Result<(), Status> {
        self.send(session_request::Kind::Close(pb::Close {})).await?;
        loop {
            if let Reply::Closed = self.receive().await? {
                return Ok(());
            }
        }
    }
}

fn required(tensor: Option<Tensor>, name: &str) -> Result<Tensor, Status> {
    tensor.ok_or_else(|| Status::internal(format!("response without {name}")))
}

async fn next_response(responses: &mut Streaming<SessionResponse>) -> Result<SessionResponse, Status> {
    responses
        .message()
        .await?
        .ok_or_else(|| Status::unavailable("the simulator worker ended the session"))
}
