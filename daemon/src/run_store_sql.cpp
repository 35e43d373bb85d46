// The run store's thin sqlite3 wrappers: see run_store_sql.hpp.
#include "run_store_sql.hpp"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <system_error>

namespace cellbench::daemon::store {

double now_unix_s() {
    return std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
}

std::string sqlite_message(sqlite3* db, int code) {
    std::string msg = db ? sqlite3_errmsg(db) : sqlite3_errstr(code);
    if (db) {
        if (const int err = sqlite3_system_errno(db); err != 0) msg += " (" + std::generic_category().message(err) + ")";
    }
    return msg;
}

void throw_sql(sqlite3* db, int code, std::string_view /*what*/) {
    const int ext = db ? sqlite3_extended_errcode(db) : code;
    throw SqlError(ext ? ext : code, sqlite_message(db, code));
}

void exec_script(sqlite3* db, const char* sql) {
    const char* tail = sql;
    while (tail && *tail) {
        sqlite3_stmt* s = nullptr;
        const int rc = sqlite3_prepare_v2(db, tail, -1, &s, &tail);
        if (rc != SQLITE_OK) throw_sql(db, rc, "prepare");
        if (!s) continue;  // whitespace / comment
        int st;
        while ((st = sqlite3_step(s)) == SQLITE_ROW) {
        }
        sqlite3_finalize(s);
        if (st != SQLITE_DONE) throw_sql(db, st, "exec");
    }
}

void exec(sqlite3* db, std::string_view sql) { Stmt(db, sql).run(); }

StoreFaultKind classify(int code) {
    switch (code & 0xff) {
        case SQLITE_FULL: return StoreFaultKind::disk_full;
        case SQLITE_BUSY:
        case SQLITE_LOCKED: return StoreFaultKind::busy;
        case SQLITE_READONLY: return StoreFaultKind::readonly;
        case SQLITE_IOERR: return StoreFaultKind::io_error;
        case SQLITE_CORRUPT:
        case SQLITE_NOTADB: return StoreFaultKind::corrupt;
        case SQLITE_CANTOPEN: return StoreFaultKind::io_error;
        default: return StoreFaultKind::other;
    }
}

std::string plain_fault(StoreFaultKind kind) {
    switch (kind) {
        case StoreFaultKind::disk_full: return "disk full (or the database size limit reached)";
        case StoreFaultKind::busy: return "database locked by another process";
        case StoreFaultKind::readonly: return "database is read-only";
        case StoreFaultKind::io_error: return "disk I/O error";
        case StoreFaultKind::corrupt: return "database file is damaged";
        case StoreFaultKind::overflow: return "writer queue full";
        case StoreFaultKind::closed: return "run store is closed";
        default: return "database error";
    }
}

void open_fail(const fs::path& path, const std::string& why) {
    throw InputError(path.string() + ": cannot use as the run database: " + why);
}

// SQLite in WAL mode creates PATH-wal and PATH-shm beside the database, so a database opened for writing needs a
// folder it can create files in. Checked by creating (and removing) a probe file, so the message says which
// folder and why (an immutable or read-only folder used to read "No such file or directory").
void check_folder_writable(const fs::path& path) {
    const fs::path parent = path.parent_path().empty() ? fs::path(".") : path.parent_path();
    std::error_code ec;
    if (!fs::is_directory(parent, ec)) return;  // reported by the open with its own message
    const fs::path probe = parent / (".cellbench-write-probe-" + std::to_string(::getpid()));
    const int fd = ::open(probe.c_str(), O_CREAT | O_EXCL | O_WRONLY | O_CLOEXEC, 0600);
    if (fd < 0) {
        const int err = errno;
        if (err == EEXIST) return;  // a leftover probe: the folder took files before
        open_fail(path, "cannot create files in the folder " + parent.string() + " (" + std::strerror(err) +
                            "): SQLite keeps " + path.filename().string() + "-wal and " + path.filename().string() +
                            "-shm beside the database, so its folder must be writable (choose another --db or "
                            "fix the folder's permissions)");
    }
    ::close(fd);
    fs::remove(probe, ec);
}

Conn open_connection(const fs::path& path, int flags, std::chrono::milliseconds busy_timeout) {
    if (flags & SQLITE_OPEN_CREATE) check_folder_writable(path);
    sqlite3* raw = nullptr;
    const int rc = sqlite3_open_v2(path.c_str(), &raw, flags | SQLITE_OPEN_NOMUTEX, nullptr);
    Conn db(raw);
    if (rc != SQLITE_OK) {
        std::string why = sqlite_message(raw, rc);
        std::error_code ec;
        const fs::path parent = path.parent_path().empty() ? fs::path(".") : path.parent_path();
        if (!fs::is_directory(parent, ec)) why = "the folder " + parent.string() + " does not exist";
        else if (fs::is_directory(path, ec)) why += " (it is a folder)";
        else if ((flags & SQLITE_OPEN_CREATE) == 0 && !fs::exists(path, ec)) why += " (no such file)";
        open_fail(path, why);
    }
    sqlite3_extended_result_codes(db.get(), 1);
    sqlite3_busy_timeout(db.get(), static_cast<int>(busy_timeout.count()));
    return db;
}

}  // namespace cellbench::daemon::store
