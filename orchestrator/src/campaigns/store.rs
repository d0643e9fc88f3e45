//! The results database: an embedded SQLite file (WAL mode) holding a campaign's
//! manifest, one summary row per trial and its per-step rows, plus CSV export.
//!
//! Each finished trial is written in a single transaction (its summary and all its step
//! rows), so a campaign killed at any moment leaves only whole trials behind and resumes
//! by skipping them; `UNIQUE(condition, task, seed)` makes running one twice impossible.
//! With WAL and `synchronous = NORMAL` a killed process loses nothing it committed; a
//! power cut may lose the last few trials, which the next invocation then runs again.
//!
//! The schema's version is SQLite's `user_version` ([`SCHEMA_VERSION`]). Version 0 (the
//! first, unversioned databases) lacks `trials.stage_wall_seconds` and the
//! `learning_steps` table: [`Store::create`] adds them (the trials stored before keep
//! NULL there), [`Store::open`] adds them too when the file is writable and otherwise
//! reads the database as it is. Version 1 lacks `sessions.shard` (the shard an
//! invocation ran, `geese campaign --shard`), added the same way.
use crate::analysis::metrics::Outcome;
use crate::campaigns::campaign::{Campaign, CampaignOutcome};
use crate::campaigns::shard::Shard;
use crate::run::output::versions;
use crate::run::trial::TrialSummary;
use geese_proto::StepReport;
use rusqlite::{params, Connection, OpenFlags, OptionalExtension};
use std::io::Write;
use std::path::{Path, PathBuf};

const SCHEMA: &str = "
CREATE TABLE IF NOT EXISTS meta (
    key   TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS sessions (
    id            INTEGER PRIMARY KEY,
    started_unix  INTEGER NOT NULL,
    finished_unix INTEGER,
    command       TEXT NOT NULL,
    versions      TEXT NOT NULL,
    campaign_digest TEXT NOT NULL,
    shard         TEXT,
    done          INTEGER,
    failed        INTEGER,
    skipped       INTEGER,
    wall_seconds  REAL
);
CREATE TABLE IF NOT EXISTS trials (
    id              INTEGER PRIMARY KEY,
    condition       TEXT NOT NULL,
    condition_index INTEGER NOT NULL,
    condition_json  TEXT NOT NULL,
    x               REAL NOT NULL,
    x_label         TEXT NOT NULL,
    series          TEXT NOT NULL,
    task            TEXT NOT NULL,
    seed            INTEGER NOT NULL,
    status          TEXT NOT NULL CHECK (status IN ('done', 'failed')),
    error           TEXT,
    session         INTEGER NOT NULL REFERENCES sessions(id),
    transport       TEXT NOT NULL,
    config          TEXT NOT NULL,
    grammar         TEXT NOT NULL,
    grammar_digest  TEXT NOT NULL,
    steps           INTEGER NOT NULL,
    final_task_pct  REAL,
    max_task_pct    REAL,
    first_step_at_threshold INTEGER,
    rows_at_threshold INTEGER,
    success         INTEGER,
    genetic_steps   INTEGER,
    stagnation_steps INTEGER,
    wall_seconds    REAL NOT NULL,
    finished_unix   INTEGER NOT NULL,
    stage_wall_seconds REAL,
    UNIQUE (condition, task, seed)
);
CREATE TABLE IF NOT EXISTS steps (
    trial            INTEGER NOT NULL REFERENCES trials(id),
    step             INTEGER NOT NULL,
    task_pct         REAL NOT NULL,
    lt_mean          REAL NOT NULL,
    lt_std           REAL NOT NULL,
    genetic_steps    INTEGER NOT NULL,
    stagnation_steps INTEGER NOT NULL,
    live_agents      INTEGER NOT NULL,
    missing_intents  INTEGER NOT NULL,
    rejected         INTEGER NOT NULL,
    genes_lost       INTEGER NOT NULL,
    PRIMARY KEY (trial, step)
) WITHOUT ROWID;
";

/// Tables and columns added after version 0 (created by [`SCHEMA`] in a new database;
/// [`Store::migrate`] adds `trials.stage_wall_seconds` to an old one).
const SCHEMA_V1: &str = "
CREATE TABLE IF NOT EXISTS learning_steps (
    trial    INTEGER NOT NULL REFERENCES trials(id),
    step     INTEGER NOT NULL,
    task_pct REAL NOT NULL,
    PRIMARY KEY (trial, step)
) WITHOUT ROWID;
";

/// Version of the schema this code writes (SQLite `user_version`): 1 added
/// `trials.stage_wall_seconds` and `learning_steps`, 2 `sessions.shard` (so that the
/// sessions of different shards stay apart when `geese merge` combines them).
pub const SCHEMA_VERSION: i32 = 2;

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("results database {path}: {source}")]
    Sql { path: PathBuf, source: rusqlite::Error },
    #[error("results database {0} does not exist")]
    Missing(PathBuf),
    #[error("results database {path} holds campaign '{stored}', not '{wanted}': use another --db or remove the file")]
    OtherCampaign { path: PathBuf, stored: String, wanted: String },
    #[error(
        "results database {path}: trial '{condition}' task {task} seed {seed} was stored with another \
         configuration than the campaign file now gives; use another --db, or restore the file"
    )]
    ConfigChanged { path: PathBuf, condition: String, task: String, seed: u64 },
    #[error("results database {path} holds {stored}, not {wanted}: use another --db")]
    OtherShard { path: PathBuf, stored: String, wanted: String },
    #[error(
        "results database {path} is a shard of the campaign resolved as {stored}, but it now resolves as \
         {wanted} (other seeds, steps, agents or grammar?): run the shards of one campaign with one \
         campaign file and the same options, or use another --db"
    )]
    ShardOfOtherCampaign { path: PathBuf, stored: String, wanted: String },
    #[error("cannot write {path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
}

/// Meta key of the digest of the resolved campaign ([`Campaign::resolved_digest`]).
pub const META_RESOLVED_DIGEST: &str = "campaign_resolved_digest";
/// Meta key of the shard (`I/N`) a database holds; absent for the whole campaign.
pub const META_SHARD: &str = "shard";
/// Meta key of the number of trials of the whole campaign (all shards).
pub const META_TRIALS_PLANNED: &str = "trials_planned";

/// Key and configuration of a trial, known before it runs.
#[derive(Clone, Debug, PartialEq)]
pub struct TrialRecord {
    pub condition: String,
    pub condition_json: String,
    pub condition_index: i64,
    pub x: f64,
    pub x_label: String,
    pub series: String,
    pub task: String,
    pub seed: u64,
    pub config_json: String,
    pub grammar: String,
    pub grammar_digest: String,
}

/// What running a trial produced.
#[derive(Clone, Debug)]
pub struct TrialResult {
    pub outcome: Outcome,
    pub summary: Option<TrialSummary>,
    /// Step rows to store (already thinned by the campaign's stride).
    pub rows: Vec<StepReport>,
    /// Set when the trial failed.
    pub error: Option<String>,
    /// The whole trial, every stage this invocation ran included (a learning stage
    /// shared with another trial is run, and counted, once).
    pub wall_seconds: f64,
    /// Steps (already thinned) of the learning stage whose population the trial tested:
    /// (step, task %); empty when the trial is itself a learning run.
    pub learning_rows: Vec<(u64, f64)>,
}

/// A trial as read back.
#[derive(Clone, Debug)]
pub struct StoredTrial {
    pub id: i64,
    pub condition: String,
    pub condition_index: i64,
    pub x: f64,
    pub x_label: String,
    pub series: String,
    pub task: String,
    pub seed: u64,
    pub error: Option<String>,
    /// `None` for a failed trial.
    pub outcome: Option<Outcome>,
    pub wall_seconds: f64,
    /// Wall time of the trial's last stage (the one whose steps are stored), as its
    /// runner measured it ([`TrialSummary::wall_seconds`]); `None` for a failed trial
    /// and for trials stored by a version-0 database.
    pub stage_wall_seconds: Option<f64>,
    /// The `geese campaign` invocation (sessions table) that ran it.
    pub session: i64,
    /// How it ran: "in-process" or "zenoh".
    pub transport: String,
}

/// One `geese campaign` invocation; `finished` is false when it was interrupted.
#[derive(Clone, Debug, PartialEq)]
pub struct Session {
    pub id: i64,
    pub finished: bool,
    pub done: usize,
    pub failed: usize,
    pub skipped: usize,
    pub wall_seconds: f64,
}

impl StoredTrial {
    /// Milliseconds of wall time per step of the trial's last stage (the paper's Fig. 9b
    /// run time), when known.
    pub fn ms_per_step(&self) -> Option<f64> {
        let steps = self.outcome.as_ref()?.steps;
        let wall = self.stage_wall_seconds?;
        (steps > 0).then(|| wall * 1000.0 / steps as f64)
    }
}

pub struct Store {
    /// Crate-visible for [`crate::campaigns::merge`], which writes a whole merge in one transaction.
    pub(crate) conn: Connection,
    path: PathBuf,
    /// The trials table has `stage_wall_seconds` (false: a read-only version-0 file).
    has_stage_wall: bool,
    /// The `learning_steps` table exists.
    has_learning: bool,
}

fn now_unix() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs() as i64).unwrap_or(0)
}

impl Store {
    fn sql<T>(&self, r: rusqlite::Result<T>) -> Result<T, StoreError> {
        r.map_err(|source| StoreError::Sql { path: self.path.clone(), source })
    }

    /// Open (creating if needed) a database for writing.
    pub fn create(path: &Path) -> Result<Store, StoreError> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|source| StoreError::Io { path: dir.into(), source })?;
        }
        let conn = Connection::open(path).map_err(|source| StoreError::Sql { path: path.into(), source })?;
        let mut s = Store { conn, path: path.into(), has_stage_wall: true, has_learning: true };
        s.sql(s.conn.busy_timeout(std::time::Duration::from_secs(30)))?;
        s.sql(s.conn.pragma_update(None, "journal_mode", "WAL"))?;
        s.sql(s.conn.pragma_update(None, "synchronous", "NORMAL"))?;
        s.sql(s.conn.execute_batch(SCHEMA))?;
        s.sql(s.migrate())?;
        s.detect()?;
        Ok(s)
    }

    /// Bring a database of an older schema version up to [`SCHEMA_VERSION`] (a no-op on
    /// a current one), in one transaction.
    fn migrate(&self) -> rusqlite::Result<()> {
        let version: i32 = self.conn.query_row("PRAGMA user_version", [], |r| r.get(0))?;
        let added = [("trials", "stage_wall_seconds", "REAL"), ("sessions", "shard", "TEXT")];
        let mut missing = Vec::new();
        for (table, column, kind) in added {
            if !self.column_exists(table, column)? {
                missing.push(format!("ALTER TABLE {table} ADD COLUMN {column} {kind}"));
            }
        }
        if version >= SCHEMA_VERSION && missing.is_empty() {
            return Ok(());
        }
        self.conn.execute_batch("BEGIN IMMEDIATE")?;
        let r = (|| {
            for alter in &missing {
                self.conn.execute_batch(alter)?;
            }
            self.conn.execute_batch(SCHEMA_V1)?;
            self.conn.pragma_update(None, "user_version", SCHEMA_VERSION)
        })();
        match r {
            Ok(()) => self.conn.execute_batch("COMMIT"),
            Err(e) => {
                let _ = self.conn.execute_batch("ROLLBACK");
                Err(e)
            }
        }
    }

    fn column_exists(&self, table: &str, column: &str) -> rusqlite::Result<bool> {
        let mut st = self.conn.prepare("SELECT 1 FROM pragma_table_info(?1) WHERE name = ?2")?;
        st.exists(params![table, column])
    }

    /// Which of the version-1 additions this database has.
    fn detect(&mut self) -> Result<(), StoreError> {
        self.has_stage_wall = self.sql(self.column_exists("trials", "stage_wall_seconds"))?;
        self.has_learning = self.sql(self.conn.query_row(
            "SELECT COUNT(*) FROM sqlite_master WHERE type = 'table' AND name = 'learning_steps'",
            [],
            |r| r.get::<_, i64>(0),
        ))? > 0;
        Ok(())
    }

    /// Open an existing database (report, export, inspection).
    pub fn open(path: &Path) -> Result<Store, StoreError> {
        if !path.exists() {
            return Err(StoreError::Missing(path.into()));
        }
        let conn =
            Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_WRITE | OpenFlags::SQLITE_OPEN_NO_MUTEX)
                .map_err(|source| StoreError::Sql { path: path.into(), source })?;
        let mut s = Store { conn, path: path.into(), has_stage_wall: true, has_learning: true };
        s.sql(s.conn.busy_timeout(std::time::Duration::from_secs(30)))?;
        // A read-only file of an older version is read as it is.
        match s.conn.execute_batch(SCHEMA).and_then(|()| s.migrate()) {
            Err(rusqlite::Error::SqliteFailure(e, _)) if e.code == rusqlite::ErrorCode::ReadOnly => {}
            r => s.sql(r)?,
        }
        s.detect()?;
        Ok(s)
    }

    /// The schema version of the database (SQLite `user_version`).
    pub fn schema_version(&self) -> Result<i32, StoreError> {
        self.sql(self.conn.query_row("PRAGMA user_version", [], |r| r.get(0)))
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// A manifest value.
    pub fn meta(&self, key: &str) -> Result<Option<String>, StoreError> {
        self.sql(self.conn.query_row("SELECT value FROM meta WHERE key = ?1", [key], |r| r.get(0)).optional())
    }

    /// Record the campaign's manifest and start a session (one `geese campaign` call).
    pub fn begin_session(&mut self, c: &Campaign) -> Result<i64, StoreError> {
        self.begin_session_in(c, None)
    }

    /// [`Store::begin_session`] of one shard of the campaign (`None`: all of it). A
    /// database holds one shard, or the unsharded campaign, for good: resuming it as
    /// another is refused. A shard's database is also refused when the campaign now
    /// resolves differently (other seeds, steps, grammar): its trials were chosen by the
    /// old campaign's partition, so the merged campaign would have gaps or strays.
    pub fn begin_session_in(&mut self, c: &Campaign, shard: Option<Shard>) -> Result<i64, StoreError> {
        let resolved = c.resolved_digest();
        if let Some(stored) = self.meta("name")? {
            if stored != c.name {
                return Err(StoreError::OtherCampaign { path: self.path.clone(), stored, wanted: c.name.clone() });
            }
            let stored = self.meta(META_SHARD)?.filter(|s| !s.is_empty());
            let wanted = shard.map(|s| s.to_string());
            if stored != wanted {
                let name = |s: Option<String>| s.map_or_else(|| "the whole campaign".into(), |s| format!("shard {s}"));
                return Err(StoreError::OtherShard {
                    path: self.path.clone(),
                    stored: name(stored),
                    wanted: name(wanted),
                });
            }
            if let (Some(_), Some(stored)) = (shard, self.meta(META_RESOLVED_DIGEST)?) {
                if stored != resolved {
                    return Err(StoreError::ShardOfOtherCampaign { path: self.path.clone(), stored, wanted: resolved });
                }
            }
        }
        let versions = serde_json::to_string(&versions()).unwrap_or_default();
        let file_json = serde_json::to_string_pretty(&c.file).unwrap_or_default();
        let conditions: Vec<serde_json::Value> = c.conditions.iter().map(|x| x.to_json()).collect();
        let entries = [
            ("name", c.name.clone()),
            ("description", c.file.description.clone()),
            ("campaign_file", c.text.clone()),
            ("campaign_resolved", file_json),
            ("campaign_digest", c.digest()),
            ("conditions", serde_json::Value::Array(conditions).to_string()),
            (
                "x",
                if c.x_by_condition {
                    "condition".into()
                } else {
                    c.x.map(|k| k.name().to_string()).unwrap_or_default()
                },
            ),
            ("series", c.series.map(|k| k.name().to_string()).unwrap_or_default()),
            ("code_efficiency", c.file.code_efficiency.map(|v| v.name().to_string()).unwrap_or_default()),
            ("threshold", c.file.base.threshold.to_string()),
            ("seeds", format!("{}..={}", c.file.first_seed, c.file.first_seed + c.file.seeds as u64 - 1)),
            (
                "seed_derivation",
                "each stream seeded with proto::seed::derive(trial seed, owner, purpose) into ChaCha8".into(),
            ),
            ("versions", versions.clone()),
            (META_RESOLVED_DIGEST, resolved),
            (META_TRIALS_PLANNED, c.plan().len().to_string()),
        ];
        let path = self.path.clone();
        let tx = self.conn.transaction().map_err(|source| StoreError::Sql { path, source })?;
        for (k, v) in entries {
            tx.execute(
                "INSERT INTO meta (key, value) VALUES (?1, ?2) ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                params![k, v],
            )
            .map_err(|source| StoreError::Sql { path: self.path.clone(), source })?;
        }
        if let Some(shard) = shard {
            tx.execute(
                "INSERT INTO meta (key, value) VALUES (?1, ?2) ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                params![META_SHARD, shard.to_string()],
            )
            .map_err(|source| StoreError::Sql { path: self.path.clone(), source })?;
        }
        tx.execute(
            "INSERT OR IGNORE INTO meta (key, value) VALUES ('created_unix', ?1)",
            params![now_unix().to_string()],
        )
        .map_err(|source| StoreError::Sql { path: self.path.clone(), source })?;
        let command = std::env::args().collect::<Vec<_>>().join(" ");
        tx.execute(
            "INSERT INTO sessions (started_unix, command, versions, campaign_digest, shard) VALUES (?1, ?2, ?3, ?4, ?5)",
            params![now_unix(), command, versions, c.digest(), shard.map(|s| s.to_string())],
        )
        .map_err(|source| StoreError::Sql { path: self.path.clone(), source })?;
        let id = tx.last_insert_rowid();
        tx.commit().map_err(|source| StoreError::Sql { path: self.path.clone(), source })?;
        Ok(id)
    }

    pub fn end_session(&self, id: i64, o: &CampaignOutcome) -> Result<(), StoreError> {
        self.sql(self.conn.execute(
            "UPDATE sessions SET finished_unix = ?2, done = ?3, failed = ?4, skipped = ?5, wall_seconds = ?6 WHERE id = ?1",
            params![id, now_unix(), o.done as i64, o.failed as i64, o.skipped as i64, o.wall_seconds],
        ))?;
        Ok(())
    }

    /// Wall time of the campaign over all its sessions (interrupted ones included) and
    /// the number of sessions. A session without a recorded wall time (killed before any
    /// trial finished, or written by an older version) counts from its start to its last
    /// finished trial.
    pub fn campaign_wall(&self) -> Result<(usize, f64), StoreError> {
        let mut stmt = self.sql(self.conn.prepare(
            "SELECT s.wall_seconds, s.started_unix, (SELECT MAX(t.finished_unix) FROM trials t WHERE t.session = s.id)
             FROM sessions s",
        ))?;
        let rows =
            self.sql(stmt.query_map([], |r| {
                Ok((r.get::<_, Option<f64>>(0)?, r.get::<_, i64>(1)?, r.get::<_, Option<i64>>(2)?))
            }))?;
        let (mut n, mut total) = (0, 0.0);
        for row in rows {
            let (wall, started, last) = self.sql(row)?;
            n += 1;
            total += wall.unwrap_or_else(|| last.map_or(0.0, |l| (l - started).max(0) as f64));
        }
        Ok((n, total))
    }

    /// Status of a stored trial with this key, checking its configuration is the same.
    pub fn find(&self, rec: &TrialRecord) -> Result<Option<String>, StoreError> {
        let row: Option<(String, String)> = self.sql(
            self.conn
                .query_row(
                    "SELECT status, config FROM trials WHERE condition = ?1 AND task = ?2 AND seed = ?3",
                    params![rec.condition, rec.task, rec.seed as i64],
                    |r| Ok((r.get(0)?, r.get(1)?)),
                )
                .optional(),
        )?;
        match row {
            Some((_, cfg)) if cfg != rec.config_json => Err(StoreError::ConfigChanged {
                path: self.path.clone(),
                condition: rec.condition.clone(),
                task: rec.task.clone(),
                seed: rec.seed,
            }),
            Some((status, _)) => Ok(Some(status)),
            None => Ok(None),
        }
    }

    /// Delete a stored trial and its steps (before retrying a failed one).
    pub fn remove(&mut self, rec: &TrialRecord) -> Result<(), StoreError> {
        let path = self.path.clone();
        let e = |source| StoreError::Sql { path: path.clone(), source };
        let tx = self.conn.transaction().map_err(e)?;
        for table in ["steps", "learning_steps"] {
            tx.execute(
                &format!(
                    "DELETE FROM {table} WHERE trial IN
                        (SELECT id FROM trials WHERE condition = ?1 AND task = ?2 AND seed = ?3)"
                ),
                params![rec.condition, rec.task, rec.seed as i64],
            )
            .map_err(e)?;
        }
        tx.execute(
            "DELETE FROM trials WHERE condition = ?1 AND task = ?2 AND seed = ?3",
            params![rec.condition, rec.task, rec.seed as i64],
        )
        .map_err(e)?;
        tx.commit().map_err(e)
    }

    /// Store a finished (or failed) trial and its step rows in one transaction, with the
    /// wall time `session` has run so far (so an invocation that is killed later still
    /// counts towards the campaign's wall time).
    pub fn insert(
        &mut self,
        rec: &TrialRecord,
        r: &TrialResult,
        session: i64,
        session_wall: f64,
        transport: &str,
    ) -> Result<(), StoreError> {
        let path = self.path.clone();
        let e = |source| StoreError::Sql { path: path.clone(), source };
        let tx = self.conn.transaction().map_err(e)?;
        let done = r.error.is_none();
        let o = &r.outcome;
        let steps: i64 = serde_json::from_str::<serde_json::Value>(&rec.config_json)
            .ok()
            .and_then(|v| v.get("steps").and_then(|s| s.as_i64()))
            .unwrap_or(o.steps as i64);
        tx.execute(
            "INSERT INTO trials (condition, condition_index, condition_json, x, x_label, series, task, seed, status, error,
                session, transport, config, grammar, grammar_digest, steps, final_task_pct, max_task_pct,
                first_step_at_threshold, rows_at_threshold, success, genetic_steps, stagnation_steps,
                wall_seconds, finished_unix, stage_wall_seconds)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16, ?17, ?18, ?19, ?20, ?21,
                ?22, ?23, ?24, ?25, ?26)",
            params![
                rec.condition,
                rec.condition_index,
                rec.condition_json,
                rec.x,
                rec.x_label,
                rec.series,
                rec.task,
                rec.seed as i64,
                if done { "done" } else { "failed" },
                r.error,
                session,
                transport,
                rec.config_json,
                rec.grammar,
                rec.grammar_digest,
                steps,
                done.then_some(o.final_pct),
                done.then_some(o.max_pct),
                if done { o.first_at_threshold.map(|v| v as i64) } else { None },
                done.then_some(o.rows_at_threshold as i64),
                done.then_some(o.success),
                r.summary.as_ref().map(|s| s.genetic_steps as i64),
                r.summary.as_ref().map(|s| s.stagnation_steps as i64),
                r.wall_seconds,
                now_unix(),
                if done { r.summary.as_ref().map(|s| s.wall_seconds) } else { None },
            ],
        )
        .map_err(e)?;
        let id = tx.last_insert_rowid();
        {
            let mut st = tx
                .prepare_cached(
                    "INSERT INTO steps (trial, step, task_pct, lt_mean, lt_std, genetic_steps, stagnation_steps,
                        live_agents, missing_intents, rejected, genes_lost)
                     VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11)",
                )
                .map_err(e)?;
            for s in &r.rows {
                st.execute(params![
                    id,
                    s.step as i64,
                    s.task_pct,
                    s.lt_mean,
                    s.lt_std,
                    s.genetic_steps,
                    s.stagnation_steps,
                    s.live_agents,
                    s.missing_intents,
                    s.rejected,
                    s.genes_lost
                ])
                .map_err(e)?;
            }
            let mut st = tx
                .prepare_cached("INSERT INTO learning_steps (trial, step, task_pct) VALUES (?1, ?2, ?3)")
                .map_err(e)?;
            for (step, pct) in &r.learning_rows {
                st.execute(params![id, *step as i64, pct]).map_err(e)?;
            }
        }
        tx.execute("UPDATE sessions SET wall_seconds = ?2 WHERE id = ?1", params![session, session_wall]).map_err(e)?;
        tx.commit().map_err(e)
    }

    /// Every stored trial, in condition, task, seed order.
    pub fn trials(&self) -> Result<Vec<StoredTrial>, StoreError> {
        let stage_wall = if self.has_stage_wall { "stage_wall_seconds" } else { "NULL" };
        let mut st = self.sql(self.conn.prepare(&format!(
            "SELECT id, condition, condition_index, x, x_label, series, task, seed, status, error, steps,
                    final_task_pct, max_task_pct, first_step_at_threshold, rows_at_threshold, success, wall_seconds,
                    session, transport, {stage_wall}
             FROM trials ORDER BY condition_index, task, seed",
        )))?;
        let rows = st.query_map([], |r| {
            let status: String = r.get(8)?;
            let outcome = if status == "done" {
                Some(Outcome {
                    steps: r.get::<_, i64>(10)? as u64,
                    final_pct: r.get(11)?,
                    max_pct: r.get(12)?,
                    first_at_threshold: r.get::<_, Option<i64>>(13)?.map(|v| v as u64),
                    rows_at_threshold: r.get::<_, i64>(14)? as u64,
                    success: r.get(15)?,
                })
            } else {
                None
            };
            Ok(StoredTrial {
                id: r.get(0)?,
                condition: r.get(1)?,
                condition_index: r.get(2)?,
                x: r.get(3)?,
                x_label: r.get(4)?,
                series: r.get(5)?,
                task: r.get(6)?,
                seed: r.get::<_, i64>(7)? as u64,
                error: r.get(9)?,
                outcome,
                wall_seconds: r.get(16)?,
                session: r.get(17)?,
                transport: r.get(18)?,
                stage_wall_seconds: r.get(19)?,
            })
        });
        let rows = self.sql(rows)?;
        let mut out = Vec::new();
        for r in rows {
            out.push(self.sql(r)?);
        }
        Ok(out)
    }

    /// Task % rows of the finished trials: calls `f(trial id, step, task %)`, ordered
    /// by trial and step.
    pub fn for_each_task_pct(&self, f: impl FnMut(i64, u64, f64)) -> Result<(), StoreError> {
        self.task_pct_rows("steps", f)
    }

    /// Task % rows of the learning stages whose populations finished trials tested, as
    /// [`Store::for_each_task_pct`] (nothing for a database without them).
    pub fn for_each_learning_pct(&self, f: impl FnMut(i64, u64, f64)) -> Result<(), StoreError> {
        if !self.has_learning {
            return Ok(());
        }
        self.task_pct_rows("learning_steps", f)
    }

    fn task_pct_rows(&self, table: &str, mut f: impl FnMut(i64, u64, f64)) -> Result<(), StoreError> {
        let mut st = self.sql(self.conn.prepare(&format!(
            "SELECT s.trial, s.step, s.task_pct FROM {table} s JOIN trials t ON t.id = s.trial
             WHERE t.status = 'done' ORDER BY s.trial, s.step"
        )))?;
        let mut rows = self.sql(st.query([]))?;
        while let Some(r) = self.sql(rows.next())? {
            let (a, b, c) = self.sql((|| Ok((r.get::<_, i64>(0)?, r.get::<_, i64>(1)?, r.get::<_, f64>(2)?)))())?;
            f(a, b as u64, c);
        }
        Ok(())
    }

    /// The `geese campaign` invocations recorded, oldest first.
    pub fn sessions(&self) -> Result<Vec<Session>, StoreError> {
        let mut st = self.sql(
            self.conn
                .prepare("SELECT id, finished_unix, done, failed, skipped, wall_seconds FROM sessions ORDER BY id"),
        )?;
        let rows = self.sql(st.query_map([], |r| {
            Ok(Session {
                id: r.get(0)?,
                finished: r.get::<_, Option<i64>>(1)?.is_some(),
                done: r.get::<_, Option<i64>>(2)?.unwrap_or(0) as usize,
                failed: r.get::<_, Option<i64>>(3)?.unwrap_or(0) as usize,
                skipped: r.get::<_, Option<i64>>(4)?.unwrap_or(0) as usize,
                wall_seconds: r.get::<_, Option<f64>>(5)?.unwrap_or(0.0),
            })
        }))?;
        let mut out = Vec::new();
        for r in rows {
            out.push(self.sql(r)?);
        }
        Ok(out)
    }

    /// Number of stored step rows of a trial.
    pub fn step_count(&self, trial: i64) -> Result<u64, StoreError> {
        self.sql(self.conn.query_row("SELECT COUNT(*) FROM steps WHERE trial = ?1", [trial], |r| r.get::<_, i64>(0)))
            .map(|n| n as u64)
    }

    /// Export the database to CSV files in `dir`: `trials.csv`, `steps.csv`,
    /// `sessions.csv`, `learning_steps.csv` (the learning stages of fixed tests; not in
    /// a read-only version-0 database) and `manifest.json` (the meta table). Returns the
    /// files written.
    pub fn export_csv(&self, dir: &Path) -> Result<Vec<PathBuf>, StoreError> {
        std::fs::create_dir_all(dir).map_err(|source| StoreError::Io { path: dir.into(), source })?;
        let mut written = Vec::new();
        let stage_wall = if self.has_stage_wall { "stage_wall_seconds" } else { "NULL AS stage_wall_seconds" };
        let mut exports = vec![
            (
                "trials.csv",
                format!(
                    "SELECT id, condition, condition_index, x, x_label, series, task, seed, status, error, session,
                        transport, grammar, grammar_digest, steps, final_task_pct, max_task_pct,
                        first_step_at_threshold, rows_at_threshold, success, genetic_steps, stagnation_steps,
                        wall_seconds, {stage_wall}, finished_unix, condition_json, config
                     FROM trials ORDER BY id"
                ),
            ),
            (
                "steps.csv",
                "SELECT s.trial, t.task, t.condition, t.seed, s.step, s.task_pct, s.lt_mean, s.lt_std, s.genetic_steps,
                        s.stagnation_steps, s.live_agents, s.missing_intents, s.rejected, s.genes_lost
                 FROM steps s JOIN trials t ON t.id = s.trial ORDER BY s.trial, s.step"
                    .to_string(),
            ),
            ("sessions.csv", "SELECT * FROM sessions ORDER BY id".to_string()),
        ];
        if self.has_learning {
            exports.push((
                "learning_steps.csv",
                "SELECT s.trial, t.task, t.condition, t.seed, s.step, s.task_pct
                 FROM learning_steps s JOIN trials t ON t.id = s.trial ORDER BY s.trial, s.step"
                    .to_string(),
            ));
        }
        for (file, query) in exports {
            let path = dir.join(file);
            self.query_to_csv(&query, &path)?;
            written.push(path);
        }
        let mut st = self.sql(self.conn.prepare("SELECT key, value FROM meta ORDER BY key"))?;
        let mut m = serde_json::Map::new();
        let rows = self.sql(st.query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, String>(1)?))))?;
        for r in rows {
            let (k, v) = self.sql(r)?;
            let value = if matches!(k.as_str(), "versions" | "conditions") {
                serde_json::from_str(&v).unwrap_or(serde_json::Value::String(v))
            } else {
                serde_json::Value::String(v)
            };
            m.insert(k, value);
        }
        let path = dir.join("manifest.json");
        let text = serde_json::to_string_pretty(&serde_json::Value::Object(m)).unwrap_or_default();
        std::fs::write(&path, text).map_err(|source| StoreError::Io { path: path.clone(), source })?;
        written.push(path);
        Ok(written)
    }

    fn query_to_csv(&self, query: &str, path: &Path) -> Result<(), StoreError> {
        let io = |source| StoreError::Io { path: path.into(), source };
        let mut out = std::io::BufWriter::new(std::fs::File::create(path).map_err(io)?);
        let mut st = self.sql(self.conn.prepare(query))?;
        let names: Vec<String> = st.column_names().iter().map(|s| s.to_string()).collect();
        let n = names.len();
        writeln!(out, "{}", names.join(",")).map_err(io)?;
        let mut rows = self.sql(st.query([]))?;
        let mut line = String::new();
        while let Some(r) = self.sql(rows.next())? {
            line.clear();
            for i in 0..n {
                if i > 0 {
                    line.push(',');
                }
                let v = self.sql(r.get_ref(i))?;
                match v {
                    rusqlite::types::ValueRef::Null => {}
                    rusqlite::types::ValueRef::Integer(x) => line.push_str(&x.to_string()),
                    rusqlite::types::ValueRef::Real(x) => line.push_str(&x.to_string()),
                    rusqlite::types::ValueRef::Text(t) => line.push_str(&csv_field(&String::from_utf8_lossy(t))),
                    rusqlite::types::ValueRef::Blob(_) => line.push_str("<blob>"),
                }
            }
            writeln!(out, "{line}").map_err(io)?;
        }
        out.flush().map_err(io)
    }
}

/// Quote a CSV field when it needs it (RFC 4180).
pub fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A database as the first, unversioned schema wrote it, with one finished trial.
    fn version_0_database(path: &Path) {
        let v0 = SCHEMA.replace("    stage_wall_seconds REAL,\n", "").replace("    shard         TEXT,\n", "");
        assert_eq!(v0.len(), SCHEMA.len() - "    stage_wall_seconds REAL,\n    shard         TEXT,\n".len());
        let conn = Connection::open(path).unwrap();
        conn.execute_batch(&v0).unwrap();
        conn.execute_batch(
            "INSERT INTO sessions (started_unix, command, versions, campaign_digest) VALUES (0, 'geese', '{}', 'd');
             INSERT INTO trials (condition, condition_index, condition_json, x, x_label, series, task, seed, status,
                error, session, transport, config, grammar, grammar_digest, steps, final_task_pct, max_task_pct,
                first_step_at_threshold, rows_at_threshold, success, genetic_steps, stagnation_steps, wall_seconds,
                finished_unix)
             VALUES ('ip=0.9', 0, '{\"ip\":0.9}', 0.9, '0.9', '', 'foraging', 1, 'done', NULL, 1, 'in-process',
                '{\"steps\":10}', 'g', 'd', 10, 90.0, 95.0, 5, 6, 1, 3, 0, 1.5, 0);
             INSERT INTO steps VALUES (1, 10, 90.0, 0, 0, 0, 0, 10, 0, 0, 0);",
        )
        .unwrap();
    }

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("geese-store-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn a_version_0_database_opens_and_is_migrated() {
        let dir = scratch("v0");
        let db = dir.join("old.sqlite");
        version_0_database(&db);
        let s = Store::open(&db).unwrap();
        assert_eq!(s.schema_version().unwrap(), SCHEMA_VERSION);
        let t = s.trials().unwrap();
        assert_eq!(t.len(), 1);
        assert_eq!((t[0].stage_wall_seconds, t[0].ms_per_step(), t[0].wall_seconds), (None, None, 1.5));
        assert_eq!(t[0].outcome.map(|o| o.final_pct), Some(90.0));
        let mut n = 0;
        s.for_each_learning_pct(|_, _, _| n += 1).unwrap();
        assert_eq!(n, 0);
        let r = crate::analysis::report::build(&s, &Default::default()).unwrap();
        assert!(r.points[0].ms_per_step.is_none() && r.conditions[0].ms_per_step.is_none());
        let files = s.export_csv(&dir.join("csv")).unwrap();
        assert!(files.iter().any(|f| f.ends_with("learning_steps.csv")));
        let trials = std::fs::read_to_string(dir.join("csv/trials.csv")).unwrap();
        assert!(trials.lines().next().unwrap().contains("stage_wall_seconds"));
        drop(s);
        // The writer opens it too (again: already current), and stores new trials' wall times.
        let s = Store::create(&db).unwrap();
        assert_eq!(s.schema_version().unwrap(), SCHEMA_VERSION);
        assert_eq!(s.trials().unwrap().len(), 1);
        drop(s);
        // The writer migrates a version-0 database itself.
        let db = dir.join("old2.sqlite");
        version_0_database(&db);
        let s = Store::create(&db).unwrap();
        assert!(s.has_stage_wall && s.has_learning);
        assert_eq!(s.schema_version().unwrap(), SCHEMA_VERSION);
        assert_eq!(s.trials().unwrap()[0].stage_wall_seconds, None);
        drop(s);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_version_1_database_gets_the_session_shard() {
        let dir = scratch("v1");
        let db = dir.join("v1.sqlite");
        let conn = Connection::open(&db).unwrap();
        conn.execute_batch(&SCHEMA.replace("    shard         TEXT,\n", "")).unwrap();
        conn.execute_batch(SCHEMA_V1).unwrap();
        conn.pragma_update(None, "user_version", 1).unwrap();
        conn.execute_batch(
            "INSERT INTO sessions (started_unix, command, versions, campaign_digest) VALUES (0, 'geese', '{}', 'd')",
        )
        .unwrap();
        drop(conn);
        let s = Store::open(&db).unwrap();
        assert_eq!(s.schema_version().unwrap(), SCHEMA_VERSION);
        assert!(s.column_exists("sessions", "shard").unwrap());
        assert_eq!(s.sessions().unwrap().len(), 1);
        drop(s);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_new_database_is_current() {
        let dir = scratch("new");
        let s = Store::create(&dir.join("new.sqlite")).unwrap();
        assert_eq!(s.schema_version().unwrap(), SCHEMA_VERSION);
        assert!(s.has_stage_wall && s.has_learning);
        drop(s);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn csv_quoting() {
        assert_eq!(csv_field("plain"), "plain");
        assert_eq!(csv_field("a,b"), "\"a,b\"");
        assert_eq!(csv_field("say \"hi\""), "\"say \"\"hi\"\"\"");
    }
}
