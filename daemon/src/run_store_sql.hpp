#pragma once
// The run store's SQLite layer (internal to daemon/src, shared by the run_store_*.cpp pieces): thin sqlite3
// wrappers (prepared statements, connections, read transactions, error classification) and the schema
// (run_store_schema.cpp). Nothing here knows about runs beyond the table layout.
#include <sqlite3.h>

#include <chrono>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <string_view>
#include <unordered_map>
#include <vector>

#include <nlohmann/json.hpp>

#include "cellbench/daemon/run_store.hpp"

namespace cellbench::daemon::store {

using nlohmann::json;
namespace fs = std::filesystem;

double now_unix_s();

// ---------------------------------------------------------------------------------------------------------
// Thin sqlite3 wrappers

struct SqlError : std::runtime_error {
    int code;
    SqlError(int c, const std::string& m) : std::runtime_error(m), code(c) {}
};

// SQLite's message plus the operating system's words when a system call failed ("... (Permission denied)").
std::string sqlite_message(sqlite3* db, int code);
[[noreturn]] void throw_sql(sqlite3* db, int code, std::string_view what);

// A prepared statement of `sql` (flags: 0 or SQLITE_PREPARE_PERSISTENT). Throws SqlError.
inline sqlite3_stmt* prepare_statement(sqlite3* db, std::string_view sql, unsigned flags) {
    sqlite3_stmt* s = nullptr;
    const int rc = sqlite3_prepare_v3(db, sql.data(), static_cast<int>(sql.size()), flags, &s, nullptr);
    if (rc != SQLITE_OK) throw_sql(db, rc, "prepare");
    return s;
}

// The statements one reader connection has prepared, kept until the store releases memory between runs: an API
// request's queries are then prepared once per connection and run instead of once per request (preparing took
// more of a small query's time than running it). The SQL texts are the store's own, a bounded set. Used by one
// lease at a time.
class StmtCache {
public:
    struct Entry {
        sqlite3_stmt* stmt;
        bool in_use;
    };

    explicit StmtCache(sqlite3* db) : db_(db) {}
    ~StmtCache() {
        for (auto& [sql, e] : stmts_) sqlite3_finalize(e.stmt);
    }
    StmtCache(const StmtCache&) = delete;
    StmtCache& operator=(const StmtCache&) = delete;
    [[nodiscard]] sqlite3* db() const { return db_; }
    // The entry for `sql`, prepared on first use, marked in use until release(); nullptr while the statement of
    // that text is in use (the caller then prepares one of its own).
    Entry* take(std::string_view sql) {
        auto it = stmts_.find(std::string(sql));
        if (it == stmts_.end())
            it = stmts_.emplace(std::string(sql), Entry{prepare_statement(db_, sql, SQLITE_PREPARE_PERSISTENT), false})
                     .first;
        if (it->second.in_use) return nullptr;
        it->second.in_use = true;
        return &it->second;
    }
    // Finalizes the statements not in use (between runs, so that their memory goes back with the page caches:
    // kept across a run's end they pinned heap that malloc_trim could otherwise return, +4 MiB in the soak).
    void clear() {
        for (auto it = stmts_.begin(); it != stmts_.end();) {
            if (it->second.in_use) {
                ++it;
                continue;
            }
            sqlite3_finalize(it->second.stmt);
            it = stmts_.erase(it);
        }
    }
    // Back into the cache, reset and unbound (so it holds no read snapshot). Entries are not moved by later
    // inserts (node-based map) and clear() keeps the ones in use.
    static void release(Entry& e) {
        sqlite3_reset(e.stmt);
        sqlite3_clear_bindings(e.stmt);
        e.in_use = false;
    }

private:
    sqlite3* db_;
    std::unordered_map<std::string, Entry> stmts_;
};

class Stmt {
public:
    Stmt(sqlite3* db, std::string_view sql, bool persistent = false)
        : db_(db), s_(prepare_statement(db, sql, persistent ? SQLITE_PREPARE_PERSISTENT : 0)) {}
    // A statement of the connection's cache (one of its own while the cached one is in use), handed back reset.
    Stmt(StmtCache& cache, std::string_view sql)
        : db_(cache.db()), entry_(cache.take(sql)), s_(entry_ ? entry_->stmt : prepare_statement(db_, sql, 0)) {}
    ~Stmt() {
        if (entry_) StmtCache::release(*entry_);
        else sqlite3_finalize(s_);
    }
    Stmt(const Stmt&) = delete;
    Stmt& operator=(const Stmt&) = delete;

    Stmt& real(int i, double v) {
        check(std::isfinite(v) ? sqlite3_bind_double(s_, i, v) : sqlite3_bind_null(s_, i));
        return *this;
    }
    Stmt& real(int i, const std::optional<double>& v) { return v ? real(i, *v) : null(i); }
    Stmt& integer(int i, std::int64_t v) {
        check(sqlite3_bind_int64(s_, i, v));
        return *this;
    }
    Stmt& integer(int i, const std::optional<std::int64_t>& v) { return v ? integer(i, *v) : null(i); }
    // The text must stay alive until the next bind of this parameter or reset (batches outlive their steps).
    Stmt& text_static(int i, std::string_view v) {
        check(sqlite3_bind_text(s_, i, v.data(), static_cast<int>(v.size()), SQLITE_STATIC));
        return *this;
    }
    Stmt& text(int i, std::string_view v) {
        check(sqlite3_bind_text(s_, i, v.data(), static_cast<int>(v.size()), SQLITE_TRANSIENT));
        return *this;
    }
    Stmt& text_or_null(int i, std::string_view v) { return v.empty() ? null(i) : text(i, v); }
    Stmt& null(int i) {
        check(sqlite3_bind_null(s_, i));
        return *this;
    }

    // True for a row, false when done; throws SqlError otherwise. A failed step leaves the statement reset:
    // SQLite refuses to bind a statement that stopped on an error and was never reset (SQLITE_MISUSE), so a
    // statement that once hit a full disk would otherwise refuse every later record, the run's abort included.
    bool step() {
        const int rc = sqlite3_step(s_);
        if (rc == SQLITE_ROW) return true;
        if (rc == SQLITE_DONE) return false;
        const int ext = sqlite3_extended_errcode(db_);
        SqlError err(ext ? ext : rc, sqlite_message(db_, rc));  // before the reset, which may touch the message
        sqlite3_reset(s_);
        throw err;
    }
    void run() {
        while (step()) {
        }
        reset();
    }
    void reset() { sqlite3_reset(s_); }

    [[nodiscard]] bool is_null(int c) const { return sqlite3_column_type(s_, c) == SQLITE_NULL; }
    [[nodiscard]] double col_real(int c) const { return is_null(c) ? kNaN : sqlite3_column_double(s_, c); }
    [[nodiscard]] std::optional<double> col_opt_real(int c) const {
        return is_null(c) ? std::nullopt : std::optional<double>(sqlite3_column_double(s_, c));
    }
    [[nodiscard]] std::int64_t col_int(int c) const { return sqlite3_column_int64(s_, c); }
    [[nodiscard]] std::string col_text(int c) const {
        const auto* p = sqlite3_column_text(s_, c);
        return p ? std::string(reinterpret_cast<const char*>(p), static_cast<std::size_t>(sqlite3_column_bytes(s_, c))) : std::string();
    }
    [[nodiscard]] json col_json(int c) const {
        if (is_null(c)) return nullptr;
        return json::parse(col_text(c), nullptr, false);  // a damaged cell reads as "discarded", never throws
    }

private:
    void check(int rc) {
        if (rc != SQLITE_OK) throw_sql(db_, rc, "bind");
    }
    sqlite3* db_;
    StmtCache::Entry* entry_ = nullptr;  // set when the statement is the cache's
    sqlite3_stmt* s_ = nullptr;
};

// Runs a fixed script (schema) statement by statement, each prepared.
void exec_script(sqlite3* db, const char* sql);
void exec(sqlite3* db, std::string_view sql);

StoreFaultKind classify(int code);
std::string plain_fault(StoreFaultKind kind);

// Open-time problems are the user's to fix (a bad --db path): InputError naming the path.
[[noreturn]] void open_fail(const fs::path& path, const std::string& why);

struct ConnCloser {
    void operator()(sqlite3* db) const { sqlite3_close_v2(db); }
};
using Conn = std::unique_ptr<sqlite3, ConnCloser>;

// Opens a connection (extended result codes, busy timeout); with SQLITE_OPEN_CREATE it first checks that the
// folder takes files (WAL needs PATH-wal and PATH-shm beside the database). Throws InputError.
Conn open_connection(const fs::path& path, int flags, std::chrono::milliseconds busy_timeout);

// One read transaction: every statement inside sees the same committed snapshot.
class ReadTxn {
public:
    explicit ReadTxn(sqlite3* db) : db_(db) { exec(db_, "BEGIN"); }
    explicit ReadTxn(const StmtCache& cache) : ReadTxn(cache.db()) {}
    ~ReadTxn() {
        try {
            exec(db_, "COMMIT");
        } catch (...) {
        }
    }

private:
    sqlite3* db_;
};

// Read errors are not the caller's input: surface them as StoreError with SQLite's words.
template <class F>
auto guarded_read(const fs::path& path, F&& f) {
    try {
        return f();
    } catch (const SqlError& e) {
        const auto kind = classify(e.code);
        throw StoreError(kind, path.string() + ": " + plain_fault(kind) + " while reading (" + e.what() + ")");
    }
}

// ---------------------------------------------------------------------------------------------------------
// Schema (run_store_schema.cpp)

// Checks that the file is ours (or empty). Throws InputError.
void check_identity(sqlite3* db, const fs::path& path, bool may_create);
// Creates the tables, indexes and rollups that are missing and stamps application_id / user_version, in one
// transaction. Throws SqlError.
void create_schema(sqlite3* db);

extern const char* const kTerminalStates;  // SQL list of the end states: "('completed',...)"

// Sources (for the window query and the export)
struct SourceDef {
    const char* name;
    const char* table;
    const char* rollup;                 // 1-second min/max table, or nullptr (chamber: ~1 Hz already)
    std::vector<const char*> channels;  // numeric columns
};
const std::vector<SourceDef>& source_defs();

// Rollups: per run and whole second of t_s, the number of samples, their first/last time and each channel's
// min and max. The writer updates them in the same transaction as the rows they summarise, so they always agree.
// A plot of a long run reads these (100x fewer rows at 100 Hz) and still shows every spike.
std::string rollup_ddl(const SourceDef& d);
std::string rollup_upsert(const SourceDef& d);

}  // namespace cellbench::daemon::store
