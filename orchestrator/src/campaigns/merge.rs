//! `geese merge`: the databases of a campaign's shards ([`crate::campaigns::shard`]) combined into
//! one results database, which `geese report` and `geese export` read as if the campaign
//! had run unsharded.
//!
//! Every input is checked before anything is written: it must be a campaign database of
//! this schema version whose resolved campaign ([`crate::campaigns::campaign::Campaign::resolved_digest`])
//! is the output's (when the output already holds one) or the first input's. The inputs
//! are then copied in a single transaction on the output, so a refused or failed merge
//! leaves the output as it was. Inputs are read with their own read-only connections
//! rather than `ATTACH`ed: SQLite refuses `ATTACH` inside a transaction and attaches at
//! most ten databases, and a job array may have hundreds of shards.
//!
//! Trials are identified by their key (condition, task, seed), as in the store. A trial
//! already in the output is not copied again: when both are finished, their results
//! (every column but the row id, session, transport and wall-clock times, and every step
//! and learning-step row) must be equal, or the merge is refused as a conflict; a failed
//! trial is no result, so a finished one replaces it and never the other way round.
//! The same shard given twice, a shard merged again after it ran more trials, or an
//! output that already holds some of the trials therefore all merge to the same result.
//! Sessions (the `geese campaign` invocations that ran the trials) are copied too, once
//! each, so the merged campaign's wall time is the sum over its shards' invocations.
use crate::campaigns::store::{
    Store, StoreError, META_RESOLVED_DIGEST, META_SHARD, META_TRIALS_PLANNED, SCHEMA_VERSION,
};
use rusqlite::types::Value;
use rusqlite::{params, params_from_iter, Connection, OpenFlags, OptionalExtension, Transaction, TransactionBehavior};
use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};

/// Meta key of the shards merged into a database (`1/4,2/4,…`).
pub const META_MERGED_SHARDS: &str = "merged_shards";

/// Trial columns that say how and when a trial ran, not what it found: they may differ
/// between two runs of the same trial.
const NOT_RESULTS: &[&str] = &["id", "session", "transport", "wall_seconds", "finished_unix", "stage_wall_seconds"];

/// Columns that identify a session (one `geese campaign` invocation): two shards started
/// in the same second with the same command line are told apart by their shard.
const SESSION_IDENTITY: &[&str] = &["started_unix", "command", "versions", "campaign_digest", "shard"];

#[derive(Debug, thiserror::Error)]
pub enum MergeError {
    #[error("nothing to merge: give at least one shard database")]
    NoInputs,
    #[error("{0} does not exist")]
    Missing(PathBuf),
    #[error("{0} is both the output and an input of the merge")]
    SameFile(PathBuf),
    #[error("{path} is not a campaign database: {why}")]
    NotCampaign { path: PathBuf, why: String },
    #[error(
        "{path} has schema version {found}, this geese writes version {expected}: shards must have one schema \
         (run `geese campaign` on it with this geese to migrate it)"
    )]
    Schema { path: PathBuf, found: i32, expected: i32 },
    #[error(
        "{0} has no resolved campaign digest (written before shards existed): run `geese campaign` on it once \
         with this geese to record it, or merge into a new file"
    )]
    NoDigest(PathBuf),
    #[error("{0}")]
    OtherCampaign(Box<Mismatch>),
    /// `trial` reads `'<condition>' task <task> seed <seed>`.
    #[error("trial {trial} has different results in {path} and in {other} ({what})")]
    Conflict { path: PathBuf, other: PathBuf, trial: String, what: String },
    #[error("{path}: {source}")]
    Sql { path: PathBuf, source: rusqlite::Error },
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// A database of another campaign than the reference (the output's, or the first
/// input's); boxed in [`MergeError`] to keep the error small.
#[derive(Debug)]
pub struct Mismatch {
    pub path: PathBuf,
    pub digest: String,
    pub name: String,
    pub reference: PathBuf,
    pub reference_digest: String,
    pub reference_name: String,
}

impl std::fmt::Display for Mismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} is not of the same campaign: its resolved campaign digest is {} (campaign '{}'), but {} has {} \
             (campaign '{}')",
            self.path.display(),
            self.digest,
            self.name,
            self.reference.display(),
            self.reference_digest,
            self.reference_name
        )
    }
}

/// A checked input (or existing output) database.
#[derive(Clone, Debug)]
pub struct Inspected {
    pub path: PathBuf,
    pub name: String,
    pub digest: String,
    /// `I/N`, or `None` for a whole (or merged) campaign.
    pub shard: Option<String>,
    pub trials: usize,
    /// Its last `geese campaign` invocation did not finish (still running, killed, or
    /// it failed).
    pub unfinished: bool,
    versions: Option<String>,
}

/// What a merge did, and what the output holds now.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MergeOutcome {
    /// Trials copied into the output.
    pub added: usize,
    /// Trials the output already held (from before, or from an earlier input) with the
    /// same results, or failed duplicates: not copied.
    pub already: usize,
    /// Failed trials in the output replaced by a finished one.
    pub replaced_failed: usize,
    /// Trials in the output now: all, finished, failed.
    pub trials: usize,
    pub done: usize,
    pub failed: usize,
    /// Trials of the whole campaign, when recorded.
    pub planned: Option<usize>,
    /// Shards merged into the output so far, by N then I.
    pub shards: Vec<String>,
    /// Shards `I/N` not merged yet, when every merged shard has the same N.
    pub missing_shards: Vec<String>,
    /// Inputs whose last invocation did not finish.
    pub unfinished: Vec<PathBuf>,
    /// The inputs were written by different geese versions (git revisions).
    pub versions_differ: bool,
}

fn sql<T>(path: &Path, r: rusqlite::Result<T>) -> Result<T, MergeError> {
    r.map_err(|source| MergeError::Sql { path: path.into(), source })
}

/// Column names of `table`, in table order.
fn columns(conn: &Connection, table: &str) -> rusqlite::Result<Vec<String>> {
    let mut st = conn.prepare("SELECT name FROM pragma_table_info(?1) ORDER BY cid")?;
    let rows = st.query_map([table], |r| r.get::<_, String>(0))?;
    rows.collect()
}

fn meta(conn: &Connection, key: &str) -> rusqlite::Result<Option<String>> {
    conn.query_row("SELECT value FROM meta WHERE key = ?1", [key], |r| r.get(0)).optional()
}

/// Check that `path` is a campaign database of the current schema, read-only. With
/// `fresh_ok` (the output), a database without tables or without a campaign yet is
/// `None` instead of an error.
pub fn inspect(path: &Path, fresh_ok: bool) -> Result<Option<Inspected>, MergeError> {
    if !path.exists() {
        return Err(MergeError::Missing(path.into()));
    }
    let not = |why: &str| MergeError::NotCampaign { path: path.into(), why: why.into() };
    let conn = sql(path, Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_ONLY))?;
    let tables: BTreeSet<String> = match conn
        .prepare("SELECT name FROM sqlite_master WHERE type = 'table'")
        .and_then(|mut st| st.query_map([], |r| r.get::<_, String>(0))?.collect())
    {
        Ok(t) => t,
        Err(rusqlite::Error::SqliteFailure(e, _)) if e.code == rusqlite::ErrorCode::NotADatabase => {
            return Err(not("not an SQLite database"))
        }
        Err(e) => return Err(MergeError::Sql { path: path.into(), source: e }),
    };
    if fresh_ok && tables.is_empty() {
        return Ok(None);
    }
    for t in ["meta", "sessions", "trials", "steps"] {
        if !tables.contains(t) {
            return Err(not(&format!("it has no `{t}` table")));
        }
    }
    let version: i32 = sql(path, conn.query_row("PRAGMA user_version", [], |r| r.get(0)))?;
    let name = sql(path, meta(&conn, "name"))?;
    let trials: i64 = sql(path, conn.query_row("SELECT COUNT(*) FROM trials", [], |r| r.get(0)))?;
    let Some(name) = name else {
        if fresh_ok && trials == 0 {
            return Ok(None);
        }
        return Err(not("it records no campaign (no name in its meta table)"));
    };
    if version != SCHEMA_VERSION && !fresh_ok {
        return Err(MergeError::Schema { path: path.into(), found: version, expected: SCHEMA_VERSION });
    }
    let digest = sql(path, meta(&conn, META_RESOLVED_DIGEST))?.ok_or_else(|| MergeError::NoDigest(path.into()))?;
    let unfinished = sql(
        path,
        conn.query_row("SELECT finished_unix IS NULL FROM sessions ORDER BY id DESC LIMIT 1", [], |r| r.get(0))
            .optional(),
    )?
    .unwrap_or(false);
    Ok(Some(Inspected {
        path: path.into(),
        name,
        digest,
        shard: sql(path, meta(&conn, META_SHARD))?.filter(|s| !s.is_empty()),
        trials: trials as usize,
        unfinished,
        versions: sql(path, meta(&conn, "versions"))?,
    }))
}

/// Merge the campaign databases `inputs` (shards, or any databases of the same resolved
/// campaign) into `out`, creating it if needed.
pub fn merge(out: &Path, inputs: &[PathBuf]) -> Result<MergeOutcome, MergeError> {
    if inputs.is_empty() {
        return Err(MergeError::NoInputs);
    }
    if let Ok(o) = out.canonicalize() {
        if let Some(p) = inputs.iter().find(|p| p.canonicalize().is_ok_and(|p| p == o)) {
            return Err(MergeError::SameFile(p.clone()));
        }
    }
    let mut checked = Vec::with_capacity(inputs.len());
    for p in inputs {
        checked.extend(inspect(p, false)?);
    }
    let existing = if out.exists() { inspect(out, true)? } else { None };
    let reference = existing.as_ref().unwrap_or(&checked[0]);
    for i in &checked {
        if i.digest != reference.digest {
            return Err(MergeError::OtherCampaign(Box::new(Mismatch {
                path: i.path.clone(),
                digest: i.digest.clone(),
                name: i.name.clone(),
                reference: reference.path.clone(),
                reference_digest: reference.digest.clone(),
                reference_name: reference.name.clone(),
            })));
        }
    }
    let mut outcome = MergeOutcome {
        unfinished: checked.iter().filter(|i| i.unfinished).map(|i| i.path.clone()).collect(),
        versions_differ: checked.iter().any(|i| i.versions != checked[0].versions),
        ..MergeOutcome::default()
    };

    let mut store = Store::create(out)?;
    let path = store.path().to_path_buf();
    let tx = sql(&path, store.conn.transaction_with_behavior(TransactionBehavior::Immediate))?;
    let mut merger = Merger::new(&tx, &path)?;
    for i in &checked {
        merger.merge_one(i, &mut outcome)?;
    }
    merger.finish(&mut outcome)?;
    drop(merger);
    sql(&path, tx.commit())?;
    Ok(outcome)
}

/// The output's side of a merge: its columns, and where each trial came from.
struct Merger<'a> {
    tx: &'a Transaction<'a>,
    out: &'a Path,
    trial_cols: Vec<String>,
    session_cols: Vec<String>,
    step_cols: Vec<String>,
    learning_cols: Vec<String>,
    /// The input each trial added by this merge came from (for a conflict's message).
    source: HashMap<(String, String, i64), PathBuf>,
    shards: BTreeSet<(u32, u32, String)>,
}

/// Equal as stored values: reals bit for bit (NaN equals NaN).
fn same(a: &Value, b: &Value) -> bool {
    match (a, b) {
        (Value::Real(x), Value::Real(y)) => x.to_bits() == y.to_bits(),
        _ => a == b,
    }
}

fn same_rows(a: &[Vec<Value>], b: &[Vec<Value>]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.len() == y.len() && x.iter().zip(y).all(|(u, v)| same(u, v)))
}

/// `I/N` as a sort key (N, I).
fn shard_key(s: &str) -> (u32, u32, String) {
    let (i, n) = s.split_once('/').unwrap_or((s, ""));
    (n.parse().unwrap_or(u32::MAX), i.parse().unwrap_or(u32::MAX), s.to_string())
}

impl<'a> Merger<'a> {
    fn new(tx: &'a Transaction<'a>, out: &'a Path) -> Result<Merger<'a>, MergeError> {
        let cols = |table: &str, skip: &str| -> Result<Vec<String>, MergeError> {
            Ok(sql(out, columns(tx, table))?.into_iter().filter(|c| c != skip).collect())
        };
        let mut shards = BTreeSet::new();
        if let Some(s) = sql(out, meta(tx, META_MERGED_SHARDS))? {
            shards.extend(s.split(',').filter(|s| !s.is_empty()).map(shard_key));
        }
        Ok(Merger {
            tx,
            out,
            trial_cols: cols("trials", "id")?,
            session_cols: cols("sessions", "id")?,
            step_cols: cols("steps", "trial")?,
            learning_cols: cols("learning_steps", "trial")?,
            source: HashMap::new(),
            shards,
        })
    }

    /// Every column the output has is in the input's `table` too (one schema).
    fn check_columns(&self, src: &Connection, input: &Path, table: &str, wanted: &[String]) -> Result<(), MergeError> {
        let have = sql(input, columns(src, table))?;
        match wanted.iter().find(|c| !have.contains(c)) {
            Some(c) => Err(MergeError::NotCampaign {
                path: input.into(),
                why: format!("its `{table}` table has no column `{c}` (another schema)"),
            }),
            None => Ok(()),
        }
    }

    fn merge_one(&mut self, input: &Inspected, outcome: &mut MergeOutcome) -> Result<(), MergeError> {
        let p = input.path.as_path();
        let src = sql(p, Connection::open_with_flags(p, OpenFlags::SQLITE_OPEN_READ_ONLY))?;
        self.check_columns(&src, p, "trials", &self.trial_cols)?;
        self.check_columns(&src, p, "sessions", &self.session_cols)?;
        self.check_columns(&src, p, "steps", &self.step_cols)?;
        self.check_columns(&src, p, "learning_steps", &self.learning_cols)?;
        self.copy_meta(&src, p)?;
        if let Some(s) = &input.shard {
            self.shards.insert(shard_key(s));
        }
        let sessions = self.copy_sessions(&src, p)?;
        self.copy_trials(&src, p, &sessions, outcome)
    }

    /// The campaign's manifest, except what describes one shard; the earliest creation
    /// time; the shards an input merged itself.
    fn copy_meta(&mut self, src: &Connection, p: &Path) -> Result<(), MergeError> {
        let mut st = sql(p, src.prepare("SELECT key, value FROM meta ORDER BY key"))?;
        let rows: Vec<(String, String)> =
            sql(p, st.query_map([], |r| Ok((r.get(0)?, r.get(1)?))).and_then(|r| r.collect()))?;
        for (k, v) in rows {
            let q = match k.as_str() {
                META_SHARD => continue,
                META_MERGED_SHARDS => {
                    self.shards.extend(v.split(',').filter(|s| !s.is_empty()).map(shard_key));
                    continue;
                }
                "created_unix" => {
                    "INSERT INTO meta (key, value) VALUES (?1, ?2) ON CONFLICT(key) DO UPDATE SET value =
                        CASE WHEN CAST(excluded.value AS INTEGER) < CAST(value AS INTEGER) THEN excluded.value
                        ELSE value END"
                }
                _ => "INSERT INTO meta (key, value) VALUES (?1, ?2) ON CONFLICT(key) DO UPDATE SET value = excluded.value",
            };
            sql(self.out, self.tx.execute(q, params![k, v]))?;
        }
        Ok(())
    }

    /// Copy the input's sessions not in the output yet (by their identity columns), and
    /// bring those already there up to date; returns input id → output id.
    fn copy_sessions(&self, src: &Connection, p: &Path) -> Result<HashMap<i64, i64>, MergeError> {
        let cols = self.session_cols.join(", ");
        let mut st = sql(p, src.prepare(&format!("SELECT id, {cols} FROM sessions ORDER BY id")))?;
        let n = self.session_cols.len();
        let rows: Vec<Vec<Value>> =
            sql(p, st.query_map([], |r| (0..=n).map(|i| r.get::<_, Value>(i)).collect()).and_then(|r| r.collect()))?;
        let at = |name: &str| self.session_cols.iter().position(|c| c == name).map(|i| i + 1);
        let identity: Vec<usize> = SESSION_IDENTITY.iter().filter_map(|c| at(c)).collect();
        let wall = at("wall_seconds");
        let find = format!(
            "SELECT id, wall_seconds FROM sessions WHERE {}",
            SESSION_IDENTITY
                .iter()
                .enumerate()
                .map(|(i, c)| format!("{c} IS ?{}", i + 1))
                .collect::<Vec<_>>()
                .join(" AND ")
        );
        let insert = format!(
            "INSERT INTO sessions ({cols}) VALUES ({})",
            (1..=n).map(|i| format!("?{i}")).collect::<Vec<_>>().join(", ")
        );
        let update = format!(
            "UPDATE sessions SET {} WHERE id = ?{}",
            self.session_cols
                .iter()
                .enumerate()
                .map(|(i, c)| format!("{c} = ?{}", i + 1))
                .collect::<Vec<_>>()
                .join(", "),
            n + 1
        );
        let mut map = HashMap::new();
        for row in rows {
            let key: Vec<&Value> = identity.iter().map(|&i| &row[i]).collect();
            let found: Option<(i64, Option<f64>)> = sql(
                self.out,
                self.tx
                    .prepare_cached(&find)
                    .and_then(|mut st| st.query_row(params_from_iter(key), |r| Ok((r.get(0)?, r.get(1)?))).optional()),
            )?;
            let old_id = match row[0] {
                Value::Integer(id) => id,
                _ => continue,
            };
            let new_id = match found {
                // The same invocation, merged before: keep the further record of it.
                Some((id, out_wall)) => {
                    let in_wall = wall.and_then(|w| match row[w] {
                        Value::Real(v) => Some(v),
                        Value::Integer(v) => Some(v as f64),
                        _ => None,
                    });
                    if in_wall.unwrap_or(0.0) > out_wall.unwrap_or(0.0) {
                        let mut values: Vec<Value> = row[1..].to_vec();
                        values.push(Value::Integer(id));
                        sql(self.out, self.tx.execute(&update, params_from_iter(values)))?;
                    }
                    id
                }
                None => {
                    sql(
                        self.out,
                        self.tx.prepare_cached(&insert).and_then(|mut st| st.execute(params_from_iter(&row[1..]))),
                    )?;
                    self.tx.last_insert_rowid()
                }
            };
            map.insert(old_id, new_id);
        }
        Ok(map)
    }

    fn copy_trials(
        &mut self,
        src: &Connection,
        p: &Path,
        sessions: &HashMap<i64, i64>,
        outcome: &mut MergeOutcome,
    ) -> Result<(), MergeError> {
        let n = self.trial_cols.len();
        let cols = self.trial_cols.join(", ");
        let at = |name: &str| self.trial_cols.iter().position(|c| c == name);
        let (Some(ci), Some(ti), Some(si), Some(st_i), Some(sess_i)) =
            (at("condition"), at("task"), at("seed"), at("status"), at("session"))
        else {
            return Err(MergeError::NotCampaign { path: self.out.into(), why: "its trials table lacks a key".into() });
        };
        let results: Vec<usize> = (0..n).filter(|&i| !NOT_RESULTS.contains(&self.trial_cols[i].as_str())).collect();
        let select = format!("SELECT id, {cols} FROM trials ORDER BY id");
        let find = format!("SELECT id, {cols} FROM trials WHERE condition = ?1 AND task = ?2 AND seed = ?3");
        let insert = format!(
            "INSERT INTO trials ({cols}) VALUES ({})",
            (1..=n).map(|i| format!("?{i}")).collect::<Vec<_>>().join(", ")
        );
        let mut st = sql(p, src.prepare(&select))?;
        let mut rows = sql(p, st.query([]))?;
        while let Some(r) = sql(p, rows.next())? {
            let mut row: Vec<Value> = sql(p, (0..=n).map(|i| r.get::<_, Value>(i)).collect())?;
            let id = row.remove(0);
            // Never skip a trial silently: a row without its key is an error.
            let (src_id, condition, task, seed) = match (&id, &row[ci], &row[ti], &row[si]) {
                (Value::Integer(id), Value::Text(c), Value::Text(t), Value::Integer(s)) => {
                    (*id, c.clone(), t.clone(), *s)
                }
                _ => {
                    let why = format!("its trial row {id:?} lacks its condition, task or seed");
                    return Err(MergeError::NotCampaign { path: p.into(), why });
                }
            };
            let done = matches!(&row[st_i], Value::Text(s) if s == "done");
            let existing: Option<Vec<Value>> = sql(
                self.out,
                self.tx.prepare_cached(&find).and_then(|mut st| {
                    st.query_row(params![condition, task, seed], |r| (0..=n).map(|i| r.get::<_, Value>(i)).collect())
                        .optional()
                }),
            )?;
            let key = (condition, task, seed);
            if let Some(mut ex) = existing {
                let Value::Integer(out_id) = ex[0] else {
                    return Err(MergeError::NotCampaign { path: self.out.into(), why: "a trial row has no id".into() });
                };
                let ex = ex.split_off(1);
                let ex_done = matches!(&ex[st_i], Value::Text(s) if s == "done");
                if !done || ex_done {
                    if done {
                        self.check_same(p, &key, src, src_id, &row, out_id, &ex, &results)?;
                    }
                    outcome.already += 1;
                    continue;
                }
                // A finished trial replaces a failed one.
                for table in ["steps", "learning_steps"] {
                    sql(self.out, self.tx.execute(&format!("DELETE FROM {table} WHERE trial = ?1"), [out_id]))?;
                }
                sql(self.out, self.tx.execute("DELETE FROM trials WHERE id = ?1", [out_id]))?;
                outcome.replaced_failed += 1;
            } else {
                outcome.added += 1;
            }
            if let Value::Integer(s) = row[sess_i] {
                row[sess_i] = Value::Integer(sessions.get(&s).copied().unwrap_or(s));
            }
            sql(self.out, self.tx.prepare_cached(&insert).and_then(|mut st| st.execute(params_from_iter(&row))))?;
            let new_id = self.tx.last_insert_rowid();
            self.copy_rows(src, p, "steps", &self.step_cols, src_id, new_id)?;
            self.copy_rows(src, p, "learning_steps", &self.learning_cols, src_id, new_id)?;
            self.source.insert(key, p.to_path_buf());
        }
        Ok(())
    }

    /// The rows of `table` of trial `id` in `conn`, by step.
    fn rows(conn: &Connection, p: &Path, table: &str, cols: &[String], id: i64) -> Result<Vec<Vec<Value>>, MergeError> {
        let mut st = sql(
            p,
            conn.prepare_cached(&format!("SELECT {} FROM {table} WHERE trial = ?1 ORDER BY step", cols.join(", "))),
        )?;
        let n = cols.len();
        sql(p, st.query_map([id], |r| (0..n).map(|i| r.get::<_, Value>(i)).collect()).and_then(|r| r.collect()))
    }

    fn copy_rows(
        &self,
        src: &Connection,
        p: &Path,
        table: &str,
        cols: &[String],
        from: i64,
        to: i64,
    ) -> Result<(), MergeError> {
        let insert = format!(
            "INSERT INTO {table} (trial, {}) VALUES (?1, {})",
            cols.join(", "),
            (2..=cols.len() + 1).map(|i| format!("?{i}")).collect::<Vec<_>>().join(", ")
        );
        let mut ins = sql(self.out, self.tx.prepare_cached(&insert))?;
        let mut st = sql(p, src.prepare_cached(&format!("SELECT {} FROM {table} WHERE trial = ?1", cols.join(", "))))?;
        let mut rows = sql(p, st.query([from]))?;
        let mut values: Vec<Value> = Vec::with_capacity(cols.len() + 1);
        while let Some(r) = sql(p, rows.next())? {
            values.clear();
            values.push(Value::Integer(to));
            for i in 0..cols.len() {
                values.push(sql(p, r.get::<_, Value>(i))?);
            }
            sql(self.out, ins.execute(params_from_iter(&values)))?;
        }
        Ok(())
    }

    /// A finished trial in both: the same results, or a conflict naming both files.
    #[allow(clippy::too_many_arguments)]
    fn check_same(
        &self,
        p: &Path,
        key: &(String, String, i64),
        src: &Connection,
        src_id: i64,
        row: &[Value],
        out_id: i64,
        ex: &[Value],
        results: &[usize],
    ) -> Result<(), MergeError> {
        let differs = |what: String| MergeError::Conflict {
            path: p.into(),
            other: self.source.get(key).cloned().unwrap_or_else(|| self.out.into()),
            trial: format!("'{}' task {} seed {}", key.0, key.1, key.2),
            what,
        };
        if let Some(&i) = results.iter().find(|&&i| !same(&row[i], &ex[i])) {
            return Err(differs(format!("column {}", self.trial_cols[i])));
        }
        for (table, cols) in [("steps", &self.step_cols), ("learning_steps", &self.learning_cols)] {
            let a = Self::rows(src, p, table, cols, src_id)?;
            let b = Self::rows(self.tx, self.out, table, cols, out_id)?;
            if !same_rows(&a, &b) {
                return Err(differs(format!("its {table} rows")));
            }
        }
        Ok(())
    }

    /// Record the shards merged, drop the shard mark of a single shard, count the
    /// output's trials.
    fn finish(&self, outcome: &mut MergeOutcome) -> Result<(), MergeError> {
        let out = self.out;
        sql(out, self.tx.execute("DELETE FROM meta WHERE key = ?1", [META_SHARD]))?;
        outcome.shards = self.shards.iter().map(|s| s.2.clone()).collect();
        if !outcome.shards.is_empty() {
            sql(
                out,
                self.tx.execute(
                    "INSERT INTO meta (key, value) VALUES (?1, ?2) ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                    params![META_MERGED_SHARDS, outcome.shards.join(",")],
                ),
            )?;
        }
        let counts: BTreeSet<u32> = self.shards.iter().map(|s| s.0).collect();
        if let (1, Some(&n)) = (counts.len(), counts.first()) {
            if n != u32::MAX {
                let have: BTreeSet<u32> = self.shards.iter().map(|s| s.1).collect();
                outcome.missing_shards = (1..=n).filter(|i| !have.contains(i)).map(|i| format!("{i}/{n}")).collect();
            }
        }
        let (all, done): (i64, i64) = sql(
            out,
            self.tx.query_row("SELECT COUNT(*), COALESCE(SUM(status = 'done'), 0) FROM trials", [], |r| {
                Ok((r.get(0)?, r.get(1)?))
            }),
        )?;
        outcome.trials = all as usize;
        outcome.done = done as usize;
        outcome.failed = (all - done) as usize;
        outcome.planned = sql(out, meta(self.tx, META_TRIALS_PLANNED))?.and_then(|v| v.parse().ok());
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::campaigns::campaign::{Campaign, CampaignOutcome};
    use crate::campaigns::shard::{self, Shard};
    use crate::campaigns::store::TrialResult;
    use crate::run::trial::TrialSummary;
    use geese_proto::StepReport;

    /// 2 conditions × 1 task × 3 seeds = 6 trials (never run: results are made up).
    fn campaign(steps: u64) -> Campaign {
        let text = format!(
            "tasks = [\"foraging\"]\nseeds = 3\n[base]\nsteps = {steps}\n[base.world]\nagents = 5\n[[grid]]\nip = [0.5, 0.9]\n"
        );
        Campaign::from_toml(&text, "made-up").expect("campaign")
    }

    /// A database of `shard` (or the whole campaign) with made-up results: trial
    /// (condition c, seed s) reaches 10·c + s + `bump` %; seed `failed` fails.
    fn database(dir: &Path, file: &str, c: &Campaign, shard: Option<Shard>, bump: f64, failed: u64) -> PathBuf {
        let path = dir.join(file);
        let mut store = Store::create(&path).expect("db");
        let session = store.begin_session_in(c, shard).expect("session");
        let plan = shard.map_or_else(|| c.plan(), |s| shard::plan(c, s));
        for t in &plan {
            let top = 10.0 * t.condition as f64 + t.seed as f64 + bump;
            let series: Vec<f64> = (1..=c.file.base.steps).map(|k| top * k as f64 / c.file.base.steps as f64).collect();
            let rows = series
                .iter()
                .enumerate()
                .map(|(k, &v)| StepReport { step: k as u64 + 1, task_pct: v, ..Default::default() })
                .collect();
            let error = (t.seed == failed).then(|| "made-up failure".to_string());
            let result = TrialResult {
                outcome: crate::analysis::metrics::outcome(&series, 80.0),
                summary: error.is_none().then(|| TrialSummary::new(t.seed)),
                rows: if error.is_none() { rows } else { Vec::new() },
                error,
                wall_seconds: 1.0 + bump,
                learning_rows: vec![(1, top)],
            };
            store.insert(&c.record(t), &result, session, 1.0, "made-up").expect("insert");
        }
        let done = CampaignOutcome { planned: plan.len(), done: plan.len(), wall_seconds: 1.0, ..Default::default() };
        store.end_session(session, &done).expect("end");
        path
    }

    fn finals(db: &Path) -> Vec<(String, u64, Option<f64>)> {
        let s = Store::open(db).expect("open");
        s.trials().expect("trials").into_iter().map(|t| (t.condition, t.seed, t.outcome.map(|o| o.final_pct))).collect()
    }

    #[test]
    fn shards_merge_once_whatever_the_order_or_repetition() {
        let dir = tempfile_dir("once");
        let c = campaign(20);
        let s1 = database(&dir, "s1.sqlite", &c, Shard::new(1, 2).ok(), 0.0, 0);
        let s2 = database(&dir, "s2.sqlite", &c, Shard::new(2, 2).ok(), 0.0, 0);
        let whole = database(&dir, "whole.sqlite", &c, None, 0.0, 0);
        let out = dir.join("out.sqlite");
        // Shard 1 of 2 alone: half the campaign, shard 2 reported missing.
        let o = merge(&out, std::slice::from_ref(&s1)).expect("merge");
        assert_eq!((o.added, o.already, o.planned), (3, 0, Some(6)));
        assert_eq!((o.shards.clone(), o.missing_shards.clone()), (vec!["1/2".into()], vec!["2/2".into()]));
        // Both, shard 1 again and twice over: each trial once.
        let o = merge(&out, &[s2.clone(), s1.clone(), s1.clone()]).expect("merge");
        assert_eq!((o.added, o.already, o.trials, o.done), (3, 6, 6, 6));
        assert!(o.missing_shards.is_empty() && o.unfinished.is_empty());
        assert_eq!(finals(&out), finals(&whole));
        let merged = Store::open(&out).expect("open");
        assert_eq!(merged.meta(META_SHARD).expect("meta"), None);
        assert_eq!(merged.meta(META_MERGED_SHARDS).expect("meta").as_deref(), Some("1/2,2/2"));
        assert_eq!(merged.meta("name").expect("meta").as_deref(), Some("made-up"));
        assert_eq!(merged.sessions().expect("sessions").len(), 2, "one session per shard invocation");
        let mut steps = 0;
        merged.for_each_task_pct(|_, _, _| steps += 1).expect("steps");
        assert_eq!(steps, 6 * 20);
        drop(merged);
        // The whole campaign's database merges in as identical duplicates.
        let o = merge(&out, &[whole]).expect("merge");
        assert_eq!((o.added, o.already, o.trials), (0, 6, 6));
        assert_eq!(Store::open(&out).expect("open").sessions().expect("sessions").len(), 3);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn conflicts_are_refused_and_finished_trials_replace_failed_ones() {
        let dir = tempfile_dir("conflict");
        let c = campaign(20);
        let s1 = database(&dir, "s1.sqlite", &c, Shard::new(1, 2).ok(), 0.0, 0);
        let other = database(&dir, "other.sqlite", &c, None, 0.5, 0);
        let out = dir.join("out.sqlite");
        merge(&out, std::slice::from_ref(&s1)).expect("merge");
        let e = merge(&out, std::slice::from_ref(&other)).expect_err("conflict").to_string();
        assert!(
            e.contains("has different results in") && e.contains("other.sqlite") && e.contains("out.sqlite"),
            "{e}"
        );
        // Refused as a whole: the output is as it was.
        assert_eq!(finals(&out), finals(&s1));
        // A conflict between two inputs names both.
        let e = merge(&dir.join("out2.sqlite"), &[s1.clone(), other]).expect_err("conflict").to_string();
        assert!(e.contains("other.sqlite") && e.contains("s1.sqlite"), "{e}");
        assert_eq!(Store::open(&dir.join("out2.sqlite")).expect("open").trials().expect("trials").len(), 0);

        // Seed 2 failed in one database and finished in the other: the finished one wins.
        let failing = database(&dir, "failing.sqlite", &c, None, 0.0, 2);
        let fine = database(&dir, "fine.sqlite", &c, None, 0.0, 0);
        let o = merge(&dir.join("a.sqlite"), &[failing.clone(), fine.clone()]).expect("merge");
        assert_eq!((o.added, o.replaced_failed, o.already, o.done), (6, 2, 4, 6));
        let o = merge(&dir.join("b.sqlite"), &[fine.clone(), failing]).expect("merge");
        assert_eq!((o.added, o.replaced_failed, o.already, o.done), (6, 0, 6, 6));
        assert_eq!(finals(&dir.join("a.sqlite")), finals(&fine));
        assert_eq!(finals(&dir.join("b.sqlite")), finals(&fine));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn other_campaigns_and_other_files_are_refused_by_name() {
        let dir = tempfile_dir("refuse");
        let s1 = database(&dir, "s1.sqlite", &campaign(20), Shard::new(1, 2).ok(), 0.0, 0);
        let longer = database(&dir, "longer.sqlite", &campaign(30), Shard::new(2, 2).ok(), 0.0, 0);
        let out = dir.join("out.sqlite");
        let e = merge(&out, &[s1.clone(), longer.clone()]).expect_err("other campaign").to_string();
        let (d1, d2) = (campaign(20).resolved_digest(), campaign(30).resolved_digest());
        assert!(e.contains("longer.sqlite") && e.contains("s1.sqlite") && e.contains(&d1) && e.contains(&d2), "{e}");
        assert!(!out.exists() || finals(&out).is_empty(), "nothing written");

        let text = dir.join("notes.txt");
        std::fs::write(&text, "not a database, but long enough to have a header of its own .......").expect("write");
        let e = merge(&out, &[s1.clone(), text]).expect_err("text").to_string();
        assert!(e.contains("notes.txt is not a campaign database: not an SQLite database"), "{e}");
        let foreign = dir.join("foreign.sqlite");
        Connection::open(&foreign).and_then(|c| c.execute_batch("CREATE TABLE t (x)")).expect("foreign");
        let e = merge(&out, std::slice::from_ref(&foreign)).expect_err("foreign").to_string();
        assert!(e.contains("foreign.sqlite is not a campaign database: it has no `meta` table"), "{e}");
        let e = merge(&foreign, std::slice::from_ref(&s1)).expect_err("foreign output").to_string();
        assert!(e.contains("foreign.sqlite is not a campaign database"), "{e}");
        let e = merge(&s1, std::slice::from_ref(&s1)).expect_err("same").to_string();
        assert!(e.contains("both the output and an input"), "{e}");
        let e = merge(&out, &[dir.join("nope.sqlite")]).expect_err("missing").to_string();
        assert!(e.contains("nope.sqlite does not exist"), "{e}");
        // A database of the longer campaign as output takes no shard of the shorter one.
        let e = merge(&longer, &[s1]).expect_err("other output").to_string();
        assert!(e.contains("s1.sqlite is not of the same campaign"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_shard_database_resumes_only_as_its_own_shard() {
        let dir = tempfile_dir("resume");
        let c = campaign(20);
        let s1 = database(&dir, "s1.sqlite", &c, Shard::new(1, 2).ok(), 0.0, 0);
        let mut store = Store::create(&s1).expect("db");
        assert!(store.begin_session_in(&c, Shard::new(1, 2).ok()).is_ok());
        let e = store.begin_session_in(&c, Shard::new(2, 2).ok()).expect_err("other shard").to_string();
        assert!(e.contains("holds shard 1/2, not shard 2/2"), "{e}");
        let e = store.begin_session_in(&c, None).expect_err("whole").to_string();
        assert!(e.contains("holds shard 1/2, not the whole campaign"), "{e}");
        let e = store.begin_session_in(&campaign(30), Shard::new(1, 2).ok()).expect_err("changed").to_string();
        assert!(e.contains("now resolves as"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    fn tempfile_dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("geese-merge-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("dir");
        dir
    }
}
