// Neware BTS API frames: byte-exact encoding, parsing of the response shapes seen in the field, framing of
// arbitrary chunks, vendor quirks, and malformed input -> ProtocolError.
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "cellbench/protocol/neware_bts.hpp"

using namespace cellbench::protocol::neware;

namespace {

const std::string kTerm = "\n\n#\r\n";

ChannelAddress ch(int chlid) { return ChannelAddress{"127.0.0.1", 24, 1, 1, chlid}; }

// The tester's own style: declaration, CRLF, two-space indent (as in responses captured from BTS 8).
std::string vendor_frame(const std::string& body) {
    return "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\r\n<bts version=\"1.0\">\r\n" + body + "</bts>" + kTerm;
}

const std::string kInquireResp = vendor_frame(
    "  <cmd>inquire_resp</cmd>\r\n"
    "  <list count=\"2\">\r\n"
    "    <inquire dev=\"22-3-2-1-10\" cycle_id=\"3\" step_id=\"8\" step_type=\"dc\" workstatus=\"working\" "
    "barcode=\"P45B-001\" current=\"-4.5012\" voltage=\"3.7312\" capacity=\"0.0375\" energy=\"0.1401\" "
    "totaltime=\"26005.3\" relativetime=\"29.9\" auxtemp=\"30.1\" auxvol=\"0\" open_or_close=\"0\" log_code=\"102000\" />\r\n"
    "    <inquire dev=\"22-3-2-2-0\" cycle_id=\"1\" step_type=\"--\" workstatus=\"finish\" barcode=\"\" current=\"0\" "
    "voltage=\"3.8834\" capacity=\"0\" energy=\"0\" totaltime=\"0\" relativetime=\"0\" open_or_close=\"0\" log_code=\"0\" />\r\n"
    "  </list>\r\n");

}  // namespace

// ---------------------------------------------------------------------------------------------------------
// Requests: byte-exact, the compact form public clients send.

TEST(NewareBtsEncode, GetChlStatusRequestIsByteExact) {
    const std::string frame = encode_request(ChannelListRequest{Command::getchlstatus, {ch(1), ch(2)}});
    EXPECT_EQ(frame,
              "<?xml version=\"1.0\" encoding=\"UTF-8\" ?><bts version=\"1.0\"><cmd>getchlstatus</cmd>"
              "<list count=\"2\">"
              "<status ip=\"127.0.0.1\" devtype=\"24\" devid=\"1\" subdevid=\"1\" chlid=\"1\">true</status>"
              "<status ip=\"127.0.0.1\" devtype=\"24\" devid=\"1\" subdevid=\"1\" chlid=\"2\">true</status>"
              "</list></bts>\n\n#\r\n");
}

TEST(NewareBtsEncode, InquireRequestIsByteExact) {
    const std::string frame = encode_request(InquireRequest{{ch(3)}, false, true});
    EXPECT_EQ(frame,
              "<?xml version=\"1.0\" encoding=\"UTF-8\" ?><bts version=\"1.0\"><cmd>inquire</cmd>"
              "<list count=\"1\">"
              "<inquire ip=\"127.0.0.1\" devtype=\"24\" devid=\"1\" subdevid=\"1\" chlid=\"3\" aux=\"0\" "
              "barcode=\"1\">true</inquire>"
              "</list></bts>\n\n#\r\n");
}

TEST(NewareBtsEncode, StartRequestCarriesPathBarcodeAndEscapes) {
    StartRequest r;
    r.entries.push_back({ch(1), "C:\\steps\\hppc.xml", "P45B&01", ""});
    r.entries.push_back({ch(2), "C:\\steps\\hppc.xml", "P45B&01", "group \"A\""});
    r.backup = BackupOptions{"C:\\data", 0, 0};
    EXPECT_EQ(encode_request(r),
              "<?xml version=\"1.0\" encoding=\"UTF-8\" ?><bts version=\"1.0\"><cmd>start</cmd><list count=\"2\">"
              "<start ip=\"127.0.0.1\" devtype=\"24\" devid=\"1\" subdevid=\"1\" chlid=\"1\" barcode=\"P45B&amp;01\">"
              "C:\\steps\\hppc.xml</start>"
              "<start ip=\"127.0.0.1\" devtype=\"24\" devid=\"1\" subdevid=\"1\" chlid=\"2\" barcode=\"P45B&amp;01\" "
              "remark=\"group &quot;A&quot;\">C:\\steps\\hppc.xml</start>"
              "<backup backupdir=\"C:\\data\" filetype=\"0\" filenametype=\"0\"/>"
              "</list></bts>\n\n#\r\n");
    // and the server side reads back exactly that
    const auto parsed = std::get<StartRequest>(parse_request(encode_request(r)));
    ASSERT_EQ(parsed.entries.size(), 2u);
    EXPECT_EQ(parsed.entries[1].step_file_path, "C:\\steps\\hppc.xml");
    EXPECT_EQ(parsed.entries[1].barcode, "P45B&01");
    EXPECT_EQ(parsed.entries[1].remark, "group \"A\"");
    EXPECT_EQ(parsed.entries[1].channel, ch(2));
    ASSERT_TRUE(parsed.backup);
    EXPECT_EQ(parsed.backup->backupdir, "C:\\data");
}

TEST(NewareBtsEncode, StopPauseContinueUseTheirOwnTag) {
    for (const auto c : {Command::stop, Command::pause, Command::continue_}) {
        const std::string frame = encode_request(ChannelListRequest{c, {ch(5)}});
        const std::string tag(command_name(c));
        EXPECT_NE(frame.find("<cmd>" + tag + "</cmd>"), std::string::npos) << frame;
        EXPECT_NE(frame.find("<" + tag + " ip=\"127.0.0.1\" devtype=\"24\" devid=\"1\" subdevid=\"1\" chlid=\"5\">true</" +
                             tag + ">"),
                  std::string::npos)
            << frame;
        const auto back = std::get<ChannelListRequest>(parse_request(frame));
        EXPECT_EQ(back.command, c);
        ASSERT_EQ(back.channels.size(), 1u);
        EXPECT_EQ(back.channels[0], ch(5));
    }
    EXPECT_THROW(encode_request(ChannelListRequest{Command::inquire, {ch(1)}}), ProtocolError);
}

TEST(NewareBtsEncode, InquireResponseIsTheTestersPrettyForm) {
    InquireEntry e;
    e.channel = {"", 24, 1, 1, 2};
    e.cycle_id = 1;
    e.step_id = 4;
    e.step_type = "dc";
    e.workstatus = ChannelStatus::working;
    e.barcode = "cell-1";
    e.current_a = -20.0;
    e.voltage_v = 3.71234;
    e.capacity_ah = 0.125;
    e.energy_wh = 0.5;
    e.total_time_s = 100.25;
    e.relative_time_s = 12.5;
    e.log_code = 102000;
    EXPECT_EQ(encode_response(InquireResponse{{e}}),
              "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\r\n<bts version=\"1.0\">\r\n"
              "  <cmd>inquire_resp</cmd>\r\n"
              "  <list count=\"1\">\r\n"
              "    <inquire dev=\"24-1-1-2-0\" cycle_id=\"1\" step_id=\"4\" step_type=\"dc\" workstatus=\"working\" "
              "barcode=\"cell-1\" current=\"-20\" voltage=\"3.7123\" capacity=\"0.125\" energy=\"0.5\" "
              "totaltime=\"100.25\" relativetime=\"12.5\" open_or_close=\"0\" log_code=\"102000\" />\r\n"
              "  </list>\r\n"
              "</bts>\n\n#\r\n");
}

// ---------------------------------------------------------------------------------------------------------
// Responses in the shapes of the notes.

TEST(NewareBtsParse, InquireResponseValuesAndDevAddress) {
    const auto r = std::get<InquireResponse>(parse_response(kInquireResp));
    ASSERT_EQ(r.channels.size(), 2u);
    const auto& a = r.channels[0];
    EXPECT_EQ(a.channel.devtype, 22);
    EXPECT_EQ(a.channel.devid, 3);
    EXPECT_EQ(a.channel.subdevid, 2);
    EXPECT_EQ(a.channel.chlid, 1);
    EXPECT_EQ(a.auxid, 10);
    EXPECT_EQ(a.cycle_id, 3);
    EXPECT_EQ(a.step_id, 8);
    EXPECT_EQ(a.step_type, "dc");
    EXPECT_EQ(a.workstatus, ChannelStatus::working);
    EXPECT_EQ(a.barcode, "P45B-001");
    EXPECT_DOUBLE_EQ(a.current_a, -4.5012);  // Neware + = charge, kept
    EXPECT_DOUBLE_EQ(a.voltage_v, 3.7312);
    EXPECT_DOUBLE_EQ(a.capacity_ah, 0.0375);
    EXPECT_DOUBLE_EQ(a.energy_wh, 0.1401);
    EXPECT_DOUBLE_EQ(a.total_time_s, 26005.3);
    EXPECT_DOUBLE_EQ(a.relative_time_s, 29.9);
    EXPECT_EQ(a.log_code, 102000);
    const auto& b = r.channels[1];
    EXPECT_EQ(b.workstatus, ChannelStatus::finish);
    EXPECT_EQ(b.step_id, 0);  // idle channels omit step_id
    EXPECT_EQ(b.step_type, "--");
}

TEST(NewareBtsParse, InquireResponseRoundTrips) {
    const auto r = std::get<InquireResponse>(parse_response(kInquireResp));
    const auto again = std::get<InquireResponse>(parse_response(encode_response(r)));
    ASSERT_EQ(again.channels.size(), r.channels.size());
    for (std::size_t i = 0; i < r.channels.size(); ++i) {
        EXPECT_TRUE(again.channels[i].channel.same_channel(r.channels[i].channel));
        EXPECT_EQ(again.channels[i].auxid, r.channels[i].auxid);
        EXPECT_DOUBLE_EQ(again.channels[i].current_a, r.channels[i].current_a);
        EXPECT_DOUBLE_EQ(again.channels[i].voltage_v, r.channels[i].voltage_v);
        EXPECT_EQ(again.channels[i].workstatus, r.channels[i].workstatus);
        EXPECT_EQ(again.channels[i].barcode, r.channels[i].barcode);
    }
}

TEST(NewareBtsParse, ChannelStatusResponseAllFiveStates) {
    const auto frame = vendor_frame(
        "  <cmd>getchlstatus_resp</cmd>\r\n  <list count=\"5\">\r\n"
        "    <status ip=\"127.0.0.1\" devtype=\"27\" devid=\"21\" subdevid=\"1\" chlid=\"1\" reservepause=\"1\">working</status>\r\n"
        "    <status ip=\"127.0.0.1\" devtype=\"27\" devid=\"21\" subdevid=\"1\" chlid=\"2\" reservepause=\"0\">stop</status>\r\n"
        "    <status ip=\"127.0.0.1\" devtype=\"27\" devid=\"21\" subdevid=\"1\" chlid=\"3\" reservepause=\"0\">finish</status>\r\n"
        "    <status ip=\"127.0.0.1\" devtype=\"27\" devid=\"21\" subdevid=\"1\" chlid=\"4\" reservepause=\"0\">protect</status>\r\n"
        "    <status ip=\"127.0.0.1\" devtype=\"27\" devid=\"21\" subdevid=\"1\" chlid=\"5\" reservepause=\"0\">pause</status>\r\n"
        "  </list>\r\n");
    const auto r = std::get<ChannelStatusResponse>(parse_response(frame));
    ASSERT_EQ(r.channels.size(), 5u);
    EXPECT_EQ(r.channels[0].status, ChannelStatus::working);
    EXPECT_TRUE(r.channels[0].reserve_pause);
    EXPECT_EQ(r.channels[1].status, ChannelStatus::stop);
    EXPECT_EQ(r.channels[2].status, ChannelStatus::finish);
    EXPECT_EQ(r.channels[3].status, ChannelStatus::protect);
    EXPECT_EQ(r.channels[4].status, ChannelStatus::pause);
    EXPECT_EQ(r.channels[4].channel, (ChannelAddress{"127.0.0.1", 27, 21, 1, 5}));
    // A word this build does not know is kept, not fatal.
    const auto odd = std::get<ChannelStatusResponse>(parse_response(vendor_frame(
        "<cmd>getchlstatus_resp</cmd><list count=\"1\"><status ip=\"1\" devtype=\"1\" devid=\"1\" subdevid=\"1\" "
        "chlid=\"1\">waiting</status></list>")));
    EXPECT_EQ(odd.channels[0].status, ChannelStatus::unknown);
    EXPECT_EQ(odd.channels[0].status_text, "waiting");
}

TEST(NewareBtsParse, DevInfoResponseSpellsChannelid) {
    const auto frame = vendor_frame(
        "  <cmd>getdevinfo_resp</cmd>\r\n  <serverip count=\"1\">\r\n    <server ip=\"127.0.0.1\" port=\"502\" />\r\n"
        "  </serverip>\r\n  <middle count=\"2\">\r\n"
        "    <channel ip=\"127.0.0.1\" devtype=\"24\" devid=\"1\" subdevid=\"1\" Channelid=\"1\">true</channel>\r\n"
        "    <channel ip=\"127.0.0.1\" devtype=\"24\" devid=\"1\" subdevid=\"1\" Channelid=\"2\">false</channel>\r\n"
        "</middle>\r\n");
    const auto r = std::get<GetDevInfoResponse>(parse_response(frame));
    ASSERT_EQ(r.servers.size(), 1u);
    EXPECT_EQ(r.servers[0].port, 502);
    ASSERT_EQ(r.channels.size(), 2u);
    EXPECT_EQ(r.channels[0].channel, ch(1));
    EXPECT_TRUE(r.channels[0].online);
    EXPECT_FALSE(r.channels[1].online);
    // encoder writes Channelid too, and reads back
    const auto again = std::get<GetDevInfoResponse>(parse_response(encode_response(r)));
    EXPECT_EQ(again.channels[1].channel, ch(2));
    EXPECT_NE(encode_response(r).find("Channelid=\"2\""), std::string::npos);
}

TEST(NewareBtsParse, CommandResponsesOkOrFalseAndWrongCountIgnored) {
    // A field example of stop_resp says count="1" over two entries: entries are counted, not trusted.
    const auto frame = vendor_frame(
        "  <cmd>stop_resp</cmd>\r\n  <list count=\"1\">\r\n"
        "    <stop ip=\"127.0.0.1\" devtype=\"27\" devid=\"21\" subdevid=\"1\" chlid=\"1\">ok</stop>\r\n"
        "    <stop ip=\"127.0.0.1\" devtype=\"27\" devid=\"21\" subdevid=\"1\" chlid=\"2\">false</stop>\r\n"
        "  </list>\r\n");
    const auto r = std::get<ChannelCommandResponse>(parse_response(frame));
    EXPECT_EQ(r.command, Command::stop);
    ASSERT_EQ(r.channels.size(), 2u);
    EXPECT_TRUE(r.channels[0].ok);
    EXPECT_FALSE(r.channels[1].ok);
    EXPECT_EQ(r.channels[1].text, "false");

    const auto start = std::get<ChannelCommandResponse>(parse_response(encode_response(
        ChannelCommandResponse{Command::start, {{ch(1), true, ""}, {ch(2), false, ""}}})));
    EXPECT_EQ(start.command, Command::start);
    EXPECT_TRUE(start.channels[0].ok);
    EXPECT_FALSE(start.channels[1].ok);
    const auto cont = std::get<ChannelCommandResponse>(
        parse_response(encode_response(ChannelCommandResponse{Command::continue_, {{ch(3), true, ""}}})));
    EXPECT_EQ(cont.command, Command::continue_);
}

TEST(NewareBtsParse, ConnectLogin) {
    const auto req = std::get<ConnectRequest>(parse_request(encode_request(ConnectRequest{})));
    EXPECT_EQ(req.username, "admin");
    EXPECT_EQ(req.type, "bfgs");
    const auto resp = std::get<ConnectResponse>(
        parse_response(vendor_frame("  <cmd>connect_resp</cmd>\r\n  <result>ok</result>\r\n")));
    EXPECT_TRUE(resp.ok);
}

TEST(NewareBtsParse, MissingNumbersAreNaN) {
    const auto r = std::get<InquireResponse>(parse_response(vendor_frame(
        "<cmd>inquire_resp</cmd><list count=\"1\"><inquire dev=\"24-1-1-1\" workstatus=\"stop\" current=\"--\" "
        "voltage=\"3.5\"/></list>")));
    ASSERT_EQ(r.channels.size(), 1u);
    EXPECT_TRUE(std::isnan(r.channels[0].current_a));
    EXPECT_TRUE(std::isnan(r.channels[0].capacity_ah));
    EXPECT_DOUBLE_EQ(r.channels[0].voltage_v, 3.5);
    EXPECT_EQ(r.channels[0].auxid, 0);  // dev without auxid accepted
}

// ---------------------------------------------------------------------------------------------------------
// Vendor quirks

TEST(NewareBtsQuirks, TypographicQuotesWhitespaceAndAttributeOrder) {
    // Typographic quotes as delimiters (sometimes mixed with ASCII ones), spaces around '=', attributes in
    // another order, odd case of attribute names, padded text values, a BOM, no declaration spacing.
    const std::string frame =
        "\xEF\xBB\xBF  <?xml version=\xE2\x80\x9D" "1.0\xE2\x80\x9D encoding=\"UTF-8\" ?>\n"
        "<bts version=\xE2\x80\x9C" "1.0\xE2\x80\x9D>\n\t<cmd> getchlstatus_resp </cmd>\n"
        "<list count = \xE2\x80\x9D" "1\xE2\x80\x9D >\n"
        "  <status chlid=\xE2\x80\x9D" "7\xE2\x80\x9D  SubDevId = \"2\xE2\x80\x9D devid=\xE2\x80\x9D" "5\""
        " ip=\xE2\x80\x9D" "192.168.1.20\xE2\x80\x9D DEVTYPE=\xE2\x80\x9D" "24\xE2\x80\x9D> Working </status>\n"
        "</list></bts>" +
        kTerm;
    const auto r = std::get<ChannelStatusResponse>(parse_response(frame));
    ASSERT_EQ(r.channels.size(), 1u);
    EXPECT_EQ(r.channels[0].channel, (ChannelAddress{"192.168.1.20", 24, 5, 2, 7}));
    EXPECT_EQ(r.channels[0].status, ChannelStatus::working);
}

TEST(NewareBtsQuirks, RequestsAsPublicClientsWriteThem) {
    // `list count = "N"` with spaces, exactly as public clients send it.
    const std::string frame =
        "<?xml version=\"1.0\" encoding=\"UTF-8\" ?><bts version=\"1.0\"><cmd>inquire</cmd><list count = \"1\">"
        "<inquire ip=\"127.0.0.1\" devtype=\"27\" devid=\"21\" subdevid=\"1\" chlid=\"1\" aux=\"0\" barcode=\"1\">true"
        "</inquire></list></bts>\n\n#\r\n";
    const auto r = std::get<InquireRequest>(parse_request(frame));
    ASSERT_EQ(r.channels.size(), 1u);
    EXPECT_EQ(r.channels[0], (ChannelAddress{"127.0.0.1", 27, 21, 1, 1}));
    EXPECT_TRUE(r.barcode);
    EXPECT_FALSE(r.aux);
}

// ---------------------------------------------------------------------------------------------------------
// Framing

TEST(NewareFrameSplitter, ByteByByte) {
    FrameSplitter s;
    std::vector<std::string> frames;
    for (const char c : kInquireResp) {
        s.feed(std::string_view(&c, 1));
        while (auto f = s.next()) frames.push_back(*f);
    }
    ASSERT_EQ(frames.size(), 1u);
    EXPECT_EQ(frames[0] + kTerm, kInquireResp);
    EXPECT_EQ(s.buffered_bytes(), 0u);
    EXPECT_EQ(s.garbage_bytes(), 0u);
}

TEST(NewareFrameSplitter, ConcatenatedFramesInOneChunk) {
    const std::string a = encode_request(ChannelListRequest{Command::getchlstatus, {ch(1)}});
    const std::string b = encode_request(InquireRequest{{ch(2)}});
    FrameSplitter s;
    s.feed(a + b + a);
    std::vector<std::string> frames;
    while (auto f = s.next()) frames.push_back(*f);
    ASSERT_EQ(frames.size(), 3u);
    EXPECT_EQ(frames[0] + kTerm, a);
    EXPECT_EQ(frames[1] + kTerm, b);
    EXPECT_EQ(frames[2] + kTerm, a);
}

TEST(NewareFrameSplitter, TerminatorSplitAcrossChunks) {
    FrameSplitter s;
    const std::string f = kInquireResp;
    s.feed(f.substr(0, f.size() - 3));  // ends with "\n\n"
    EXPECT_FALSE(s.next());
    s.feed(f.substr(f.size() - 3, 2));  // "#\r"
    EXPECT_FALSE(s.next());
    s.feed(f.substr(f.size() - 1));
    const auto got = s.next();
    ASSERT_TRUE(got);
    EXPECT_NO_THROW(parse_response(*got));
}

TEST(NewareFrameSplitter, GarbageBetweenFramesIsDroppedAndCounted) {
    const std::string a = encode_request(ChannelListRequest{Command::getchlstatus, {ch(1)}});
    const std::string garbage1("\x00\xff noise #\r\n", 12);  // binary junk, even a '#' line
    const std::string garbage2 = "\n\n#\r\n";             // a stray terminator
    const std::string truncated = a.substr(0, 60);       // a frame cut off mid-way (never terminated)
    FrameSplitter s;
    s.feed(garbage1 + a + garbage2 + truncated + a + "junk");
    std::vector<std::string> frames;
    while (auto f = s.next()) frames.push_back(*f);
    ASSERT_EQ(frames.size(), 2u);
    EXPECT_EQ(frames[0] + kTerm, a);
    EXPECT_EQ(frames[1] + kTerm, a);  // the truncated frame before it was garbage, not glued on
    EXPECT_EQ(s.garbage_bytes(), garbage1.size() + truncated.size());
    EXPECT_EQ(s.buffered_bytes(), 4u);  // "junk" waits for a terminator
}

TEST(NewareFrameSplitter, MemoryABurstOfGarbageGrewIsGivenBackOnceConsumed) {
    // A daemon running for weeks must not keep, per connection, the largest buffer a burst of junk or one big
    // frame ever made it grow to (up to max_frame_bytes, 4 MiB).
    FrameSplitter s;
    const std::string a = encode_request(InquireRequest{{ch(1)}});
    s.feed(std::string(2u << 20, 'z') + "#\r\n" + a);
    std::vector<std::string> frames;
    while (auto f = s.next()) frames.push_back(*f);
    ASSERT_EQ(frames.size(), 1u);
    EXPECT_EQ(frames[0] + kTerm, a);
    EXPECT_GE(s.capacity_bytes(), 2u << 20);  // not yet: bytes are released on the next feed
    s.feed(a);
    ASSERT_TRUE(s.next());
    EXPECT_LE(s.capacity_bytes(), FrameSplitter::kKeptCapacity) << "the burst's buffer is still held";
    s.feed(std::string(1u << 20, 'q'));  // garbage still waiting for a terminator is kept (it may be a frame)
    EXPECT_GE(s.buffered_bytes(), (1u << 20) - 3);
    s.clear();
    EXPECT_LE(s.capacity_bytes(), FrameSplitter::kKeptCapacity);
}

TEST(NewareFrameSplitter, OversizedFrameRaisesThenRecovers) {
    FrameSplitter s(256);
    const std::string ok = encode_request(InquireRequest{{ch(1)}});
    ASSERT_LT(ok.size(), 256u);
    const std::string big = "<?xml version=\"1.0\"?><bts>" + std::string(1000, 'x') + "</bts>" + kTerm;
    // Complete but too large.
    s.feed(big + ok);
    EXPECT_THROW(s.next(), ProtocolError);
    auto f = s.next();
    ASSERT_TRUE(f);
    EXPECT_EQ(*f + kTerm, ok);
    // Unterminated and growing past the limit: error once, then skip to its end and continue.
    FrameSplitter t(256);
    t.feed("<?xml version=\"1.0\"?><bts>" + std::string(300, 'y'));
    EXPECT_THROW(t.next(), ProtocolError);
    EXPECT_LE(t.buffered_bytes(), 4u);  // bounded
    t.feed(std::string(5000, 'y'));
    EXPECT_FALSE(t.next());
    EXPECT_LE(t.buffered_bytes(), 4u);
    t.feed("</bts>" + kTerm + ok);
    f = t.next();
    ASSERT_TRUE(f);
    EXPECT_EQ(*f + kTerm, ok);
}

// ---------------------------------------------------------------------------------------------------------
// Malformed input

TEST(NewareBtsMalformed, EveryBrokenFrameIsAProtocolError) {
    const std::vector<std::string> bad = {
        "",
        "   \r\n",
        "not xml at all",
        "<?xml version=\"1.0\"?><bts version=\"1.0\"><cmd>inquire_resp</cmd><list>",  // unclosed
        "<?xml version=\"1.0\"?><bts><list/></bts>",                                   // no cmd
        "<?xml version=\"1.0\"?><bts><cmd></cmd></bts>",                               // empty cmd
        "<?xml version=\"1.0\"?><bts><cmd>selfdestruct_resp</cmd></bts>",              // unknown command
        "<?xml version=\"1.0\"?><bts><cmd>inquire</cmd></bts>",                        // request, not response
        "<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd></bts>",                   // no list
        "<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd></bts><bts/>",             // two roots
        "<?xml version=\"1.0\"?><other><cmd>inquire_resp</cmd></other>",               // wrong root
        "<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd><list><inquire voltage=\"3\"/></list></bts>",  // no dev
        "<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd><list><inquire dev=\"1-2-x-4-0\"/></list></bts>",
        "<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd><list><inquire dev=\"1-2-3\"/></list></bts>",
        "<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd><list><inquire dev=\"1-2-3-4-5-6\"/></list></bts>",
        "<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd><list><inquire dev=\"1-2-3-4-0\" voltage=\"3,7\"/></list></bts>",
        "<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd><list><inquire dev=\"1-2-3-4-0\" current=\"nan\"/></list></bts>",
        "<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd><list><inquire dev=\"1-2-3-4-0\" step_id=\"99999999999\"/></list></bts>",
        "<?xml version=\"1.0\"?><bts><cmd>getchlstatus_resp</cmd><list><status ip=\"1\" devtype=\"1\" devid=\"1\" "
        "subdevid=\"1\">working</status></list></bts>",  // no chlid
        "<?xml version=\"1.0\"?><bts><cmd>getchlstatus_resp</cmd><list><status ip=\"1\" devtype=\"-1\" devid=\"1\" "
        "subdevid=\"1\" chlid=\"1\">working</status></list></bts>",  // negative
        "<?xml version=\"1.0\"?><bts><cmd>getchlstatus_resp</cmd><list><status ip=\"1\" devtype=\"1\" devid=\"1\" "
        "subdevid=\"1\" chlid=\"1\"></status></list></bts>",  // no status text
        "<?xml version=\"1.0\"?><!DOCTYPE bts [<!ENTITY a \"aaaa\">]><bts><cmd>inquire_resp</cmd></bts>",
        std::string("<?xml version=\"1.0\"?><bts><cmd>inquire_resp") + std::string(1, '\0') + "</cmd></bts>",
        "<?xml version=\"1.0\"?><bts><cmd>connect_resp</cmd></bts>",  // no result
        "<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd><list><inquire dev=\"1-2-3-4-0\" a=\"1\" a=\"2\"</list></bts>",
        "<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd><list><inquire dev=\"1-2-3-4-0\" <x/></list></bts>",
    };
    for (const auto& frame : bad) {
        EXPECT_THROW(parse_response(frame), ProtocolError) << "frame: " << frame;
    }
    // Deep nesting is refused before the parser recurses.
    std::string deep = "<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd>";
    for (int i = 0; i < 100000; ++i) deep += "<a>";
    EXPECT_THROW(parse_response(deep), ProtocolError);
    // Requests too.
    EXPECT_THROW(parse_request("<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd></bts>"), ProtocolError);
    EXPECT_THROW(parse_request("<?xml version=\"1.0\"?><bts><cmd>start</cmd><list><start ip=\"1\" devtype=\"1\" "
                               "devid=\"1\" subdevid=\"1\" chlid=\"1\" barcode=\"x\">  </start></list></bts>"),
                 ProtocolError);  // no step file path
}

TEST(NewareBtsMalformed, ErrorsSayWhatWasExpected) {
    try {
        parse_response("<?xml version=\"1.0\"?><bts><cmd>inquire_resp</cmd><list><inquire dev=\"1-2-3-4-0\" "
                       "voltage=\"abc\"/></list></bts>");
        FAIL() << "no exception";
    } catch (const ProtocolError& e) {
        const std::string what = e.what();
        EXPECT_NE(what.find("voltage"), std::string::npos) << what;
        EXPECT_NE(what.find("expected a number"), std::string::npos) << what;
        EXPECT_NE(what.find("'abc'"), std::string::npos) << what;
    }
}

TEST(NewareBtsFormat, NumbersTrimmedNeverNegativeZero) {
    EXPECT_EQ(format_number(3.71234, 4), "3.7123");
    EXPECT_EQ(format_number(-20.0, 4), "-20");
    EXPECT_EQ(format_number(-0.00001, 4), "0");
    EXPECT_EQ(format_number(0.5, 6), "0.5");
    EXPECT_EQ(format_number(std::nan(""), 4), "--");
    EXPECT_EQ(frame_command(kInquireResp), "inquire_resp");
}

// ---------------------------------------------------------------------------------------------------------
// download: the tester's recorded data.

TEST(NewareBtsDownload, RequestIsOneElementWithTestAndPosition) {
    DownloadRequest r;
    r.channel = ch(2);
    r.testid = 7;
    r.startpos = 1001;
    r.count = 1000;
    const std::string frame = encode_request(r);
    EXPECT_EQ(frame,
              "<?xml version=\"1.0\" encoding=\"UTF-8\" ?><bts version=\"1.0\"><cmd>download</cmd>"
              "<download ip=\"127.0.0.1\" devtype=\"24\" devid=\"1\" subdevid=\"1\" chlid=\"2\" auxid=\"0\" testid=\"7\" "
              "startpos=\"1001\" count=\"1000\"/></bts>" + kTerm);
    const auto back = std::get<DownloadRequest>(parse_request(frame));
    EXPECT_EQ(back.channel, ch(2));
    EXPECT_EQ(back.testid, 7);
    EXPECT_EQ(back.startpos, 1001);
    EXPECT_EQ(back.count, 1000);
    r.count = 1001;  // the API's limit per request
    EXPECT_THROW(encode_request(r), ProtocolError);
}

TEST(NewareBtsDownload, ResponseRowsRoundTripWithTestTimeInMilliseconds) {
    DownloadResponse r;
    r.channel = ch(1);
    r.testid = 3;
    r.startpos = 41;
    for (int i = 0; i < 3; ++i) {
        DownloadRecord d;
        d.seqid = 41 + i;
        d.step_id = 8;
        d.cycle_id = 2;
        d.step_type = i == 0 ? "rest" : "dc";
        d.test_time_s = 26005.3 + 0.1 * i;
        d.voltage_v = 3.7312 - 0.01 * i;
        d.current_a = i == 0 ? 0.0 : -1.5004;
        d.capacity_ah = 0.000042 * i;
        d.energy_wh = 0.000156 * i;
        r.records.push_back(d);
    }
    const std::string frame = encode_response(r);
    EXPECT_NE(frame.find("testtime=\"26005300\""), std::string::npos) << frame;
    const auto back = std::get<DownloadResponse>(parse_response(frame));
    EXPECT_TRUE(back.channel.same_channel(ch(1)));  // the real server's <download> carries no ip
    EXPECT_EQ(back.testid, 3);
    ASSERT_EQ(back.records.size(), 3u);
    for (std::size_t i = 0; i < 3; ++i) {
        EXPECT_EQ(back.records[i].seqid, r.records[i].seqid);
        EXPECT_EQ(back.records[i].step_type, r.records[i].step_type);
        EXPECT_NEAR(back.records[i].test_time_s, r.records[i].test_time_s, 5e-4);
        EXPECT_DOUBLE_EQ(back.records[i].voltage_v, r.records[i].voltage_v);
        EXPECT_DOUBLE_EQ(back.records[i].current_a, r.records[i].current_a);
    }
    // An empty answer (nothing new recorded) is a valid answer.
    r.records.clear();
    EXPECT_TRUE(std::get<DownloadResponse>(parse_response(encode_response(r))).records.empty());
}

TEST(NewareBtsDownload, BrokenRowsAreProtocolErrors) {
    auto frame = [](const std::string& rows) {
        return vendor_frame("  <cmd>download_resp</cmd>\r\n  <download ip=\"127.0.0.1\" devtype=\"24\" devid=\"1\" "
                            "subdevid=\"1\" chlid=\"1\" testid=\"1\" startpos=\"1\" />\r\n  <list count=\"9\">\r\n" +
                            rows + "  </list>\r\n");
    };
    const std::string ok = "<data seqid=\"1\" stepid=\"1\" cycleid=\"1\" steptype=\"rest\" testtime=\"100\" volt=\"3.9\" "
                           "curr=\"0\" cap=\"0\" eng=\"0\" />";
    EXPECT_EQ(std::get<DownloadResponse>(parse_response(frame(ok))).records.size(), 1u);
    // No seqid, no test time, a seqid going backwards, a number that is not one.
    EXPECT_THROW(parse_response(frame("<data stepid=\"1\" testtime=\"100\" volt=\"3.9\" />")), ProtocolError);
    EXPECT_THROW(parse_response(frame("<data seqid=\"1\" stepid=\"1\" volt=\"3.9\" />")), ProtocolError);
    EXPECT_THROW(parse_response(frame(ok + ok)), ProtocolError);
    EXPECT_THROW(parse_response(frame("<data seqid=\"1\" testtime=\"100\" volt=\"3,9\" />")), ProtocolError);
    // A request without its element, or asking for more rows than the API allows.
    EXPECT_THROW(parse_request("<?xml version=\"1.0\"?><bts version=\"1.0\"><cmd>download</cmd></bts>"), ProtocolError);
    EXPECT_THROW(parse_request("<?xml version=\"1.0\"?><bts version=\"1.0\"><cmd>download</cmd><download ip=\"1\" "
                               "devtype=\"24\" devid=\"1\" subdevid=\"1\" chlid=\"1\" startpos=\"1\" count=\"5000\"/></bts>"),
                 ProtocolError);
}

// ---------------------------------------------------------------------------------------------------------
// Requests as public BTS 8 clients write them.

TEST(NewareBtsRealClients, StartWithBackupAndAStrayQuoteBeforeTheEnd) {
    const std::string frame =
        "<?xml version=\"1.0\" encoding=\"UTF-8\" ?><bts version=\"1.0\"><cmd>start</cmd><list count = \"1\">"
        "<start ip=\"127.0.0.1\" devtype=\"27\" devid=\"21\" subdevid=\"1\" chlid=\"1\" barcode=\"cell-01\">"
        "C:\\steps\\hppc.xml</start><backup backupdir=\"C:\\Neware data\\\" remotedir=\"\" filenametype=\"0\" "
        "customfilename=\"\" addtimewhenrepeat=\"0\" createdirbydate=\"0\" filetype=\"1\" backupontime=\"1\" "
        "backupontimeinterval=\"720\" backupfree=\"1\" /></list>\"</bts>\n\n#\r\n";
    const auto r = std::get<StartRequest>(parse_request(frame));
    ASSERT_EQ(r.entries.size(), 1u);
    EXPECT_EQ(r.entries[0].channel, (ChannelAddress{"127.0.0.1", 27, 21, 1, 1}));
    EXPECT_EQ(r.entries[0].step_file_path, "C:\\steps\\hppc.xml");
    EXPECT_EQ(r.entries[0].barcode, "cell-01");
    ASSERT_TRUE(r.backup);
    EXPECT_EQ(r.backup->backupdir, "C:\\Neware data\\");
    EXPECT_EQ(r.backup->filetype, 1);
}

TEST(NewareBtsRealClients, NewCommandsRoundTrip) {
    const ChannelAddress c{"", 27, 21, 1, 3};
    const auto df = std::get<ChannelListRequest>(parse_request(encode_request(ChannelListRequest{Command::inquiredf, {c}})));
    EXPECT_EQ(df.command, Command::inquiredf);
    EXPECT_EQ(df.channels.at(0), c);
    const auto off = std::get<ChannelListRequest>(parse_request(encode_request(ChannelListRequest{Command::light, {c}, false})));
    EXPECT_EQ(off.command, Command::light);
    EXPECT_FALSE(off.on);
    for (const auto cmd : {Command::downloadlog, Command::downloadStepLayer}) {
        const auto t = std::get<TestRequest>(parse_request(encode_request(TestRequest{cmd, c, 143})));
        EXPECT_EQ(t.command, cmd);
        EXPECT_EQ(t.testid, 143);
        EXPECT_TRUE(t.channel.same_channel(c));
    }
    // The test-id query: startpos 0 with count 0 is valid, startpos 0 with rows is not.
    const std::string id = "<?xml version=\"1.0\"?><bts><cmd>download</cmd><download devtype=\"27\" devid=\"21\" "
                           "subdevid=\"1\" chlid=\"1\" auxid=\"0\" testid=\"0\" startpos=\"0\" count=\"0\"/></bts>";
    const auto q = std::get<DownloadRequest>(parse_request(id));
    EXPECT_EQ(q.count, 0);
    EXPECT_EQ(q.startpos, 0);
    std::string rows = id;
    rows.replace(rows.find("count=\"0\""), 9, "count=\"10\"");
    EXPECT_THROW(parse_request(rows), ProtocolError);
    // A request for a command nobody knows is a ProtocolError naming it (the simulator answers it with an error).
    try {
        parse_request("<?xml version=\"1.0\"?><bts><cmd>goto</cmd></bts>");
        ADD_FAILURE() << "no error";
    } catch (const ProtocolError& e) {
        EXPECT_NE(std::string(e.what()).find("unknown command 'goto'"), std::string::npos) << e.what();
    }
    ErrorResponse err{"goto", "unknown command 'goto'"};
    const auto back = std::get<ErrorResponse>(parse_response(encode_response(err)));
    EXPECT_EQ(back.command, "goto");
    EXPECT_EQ(back.message, "unknown command 'goto'");
}

TEST(NewareFrameSplitter, FrameEndsAtBtsCloseWithOrWithoutTheBlankLine) {
    const std::string body = "<?xml version=\"1.0\"?><bts version=\"1.0\"><cmd>connect_resp</cmd><result>ok</result></bts>";
    FrameSplitter s;
    s.feed(body + "#\r\n" + body + "\r\n#\r\n" + "junk #\r\n" + body + "\n\n#\r\n");
    std::vector<std::string> frames;
    while (auto f = s.next()) frames.push_back(*f);
    ASSERT_EQ(frames.size(), 3u);
    for (const auto& f : frames) EXPECT_EQ(f, body);
    EXPECT_EQ(s.garbage_bytes(), 8u);  // "junk #\r\n": a '#' line that does not follow </bts>
}
